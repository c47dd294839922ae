"""One exception hierarchy for railtraj.

Every message says what is wrong *and* how to fix it (or lists the valid choices), in one line,
because the command line prints ``str(error)`` as the whole diagnosis. Library code raises these;
only :mod:`railtraj.cli` turns them into exit codes.
"""

from __future__ import annotations


class RailtrajError(Exception):
    """Base class: anything railtraj reports to the user as a one-line reason."""


class InputError(RailtrajError):
    """Bad user input: a file, a folder or a value that railtraj cannot work with."""


class SurveyError(InputError):
    """The survey folder does not follow the layout of SPEC.md."""


class FormatError(InputError):
    """A file is corrupt or not in the format its name or caller promises."""


class TrajectoryError(InputError):
    """A trajectory is malformed, unsorted, or does not cover the times asked of it."""


class CRSError(InputError):
    """A coordinate transformation cannot be done accurately (wrong CRS or missing grids)."""


class OutputError(InputError):
    """The output folder cannot be created or written (out_dir is a file, or not writable)."""


class PluginError(RailtrajError):
    """A plugin failed to import, registered something invalid, or was not found."""


class ConfigError(RailtrajError):
    """A configuration value is out of range or inconsistent."""


class MemoryLimitError(RailtrajError):
    """The job used more memory than ``max_memory_gb`` and was stopped."""


class NoOverlapError(InputError):
    """The runs of a survey share no tiles, so nothing can be matched."""
