"""Errors a user can act on: printed by the CLI as one line, no traceback."""


class UserError(RuntimeError):
    """Bad input (file, parameter, environment) described in one sentence.

    The message names the file or option at fault and, where there is one,
    the fix.
    """
