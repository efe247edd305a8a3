"""Errors a user can act on: printed by the CLI as one line, no traceback."""


class UserError(RuntimeError):
    """Bad input (file, parameter, environment) described in one sentence.

    The message names the file or option at fault and, where there is one,
    the fix.
    """


def mitsuba_message(exc) -> str:
    """Mitsuba's error text as one line, with everything useful in it.

    Mitsuba's messages span several lines: a ``[parser.cpp:444]`` prefix and
    the file and line, then details (the unreferenced properties, one per
    line) or a Python plugin's whole traceback. The last line alone loses the
    file and line or the property's name; this keeps the location, the
    details and a plugin's own error message, and drops source locations and
    traceback frames.
    """
    import re
    text = str(exc).strip()
    if not text:
        return type(exc).__name__
    parts, in_traceback = [], False
    for line in text.splitlines():
        line = re.sub(r"^\s*\[[\w.]+:\d+\]\s*", "", line).rstrip()
        if "Traceback (most recent call last):" in line:
            line = line.split("Traceback (most recent call last):")[0].rstrip()
            in_traceback = True
            if line:
                parts.append(line)
            continue
        if in_traceback:
            if line.startswith("  ") or not line.strip():
                continue           # a frame ("File ..., line N") or its source line
            in_traceback = False
            line = re.sub(r"^[A-Za-z_][\w.]*(Error|Exception): ", "", line)
        if line.strip():
            parts.append(line.strip())
    return " ".join(parts)
