"""User-facing errors. Each says what went wrong and with which file, in one line."""


class NocalError(Exception):
    """An error meant for the user: the CLI prints it as one line, without a traceback."""


class BagError(NocalError):
    """A rosbag cannot be read or holds nothing usable (missing topic, bad encoding, corruption)."""


class CheckpointError(NocalError):
    """A model file is missing, corrupt, truncated, or does not match what is asked of it."""


class ConfigError(NocalError):
    """A configuration or camera file is malformed or has invalid values."""


class DatasetError(NocalError):
    """A dataset to import does not match its format; the message names the file (and the line)."""
