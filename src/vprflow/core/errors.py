"""The errors vprflow raises for bad input, each a ``ValueError`` whose message names the
file, key or value at fault. A leaf: every wing raises them, so none owns them."""


class ConfigError(ValueError):
    """Invalid configuration; the message names the key at fault."""


class PlanError(ValueError):
    """A config that passes the schema but refers to something that does not exist (a
    method, backbone, file, ...), or a target that is not in its plan."""


class DatasetError(ValueError):
    """Bad dataset input; the message names the folder, file or value at fault."""


def short_repr(value, limit: int = 60, quote: bool = True) -> str:
    """``repr(value)`` (or the text itself with ``quote=False``) cut to about ``limit``
    characters, saying how long it was, for quoting a bad value in a message."""
    text = repr(value) if quote else str(value)
    if len(text) <= limit:
        return text
    return f"{text[: max(limit - 30, 20)]}... ({len(text)} characters)"
