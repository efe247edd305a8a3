"""Sub-commands of ``mi-invrgbl``: one module each, with ``add_parser`` and ``run``."""
