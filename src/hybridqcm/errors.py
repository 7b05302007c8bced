"""The project's user-facing errors: one hierarchy, one-line messages naming file, key and value.

Library code raises these; the apps print them in one line and exit with code 2
(apps.common.fail). Each is a ValueError, so callers that caught ValueError still do.

    HybridQCMError
    ├── ConfigError       an invalid setting or combination of settings
    ├── DatasetError      a dataset file that cannot be used (or written)
    └── CheckpointError   a checkpoint that is missing, unreadable, foreign, refused or of the wrong kind
"""

from __future__ import annotations


class HybridQCMError(ValueError):
    """Base of every user-facing error of hybridqcm."""


class ConfigError(HybridQCMError):
    """An invalid setting or combination of settings, reported before any work; names key and value."""


class DatasetError(HybridQCMError):
    """A dataset file that cannot be used; the message names the file, key and value at fault."""


class CheckpointError(HybridQCMError):
    """A checkpoint that is missing, unreadable, not ours, refused by the allow-list, or of the wrong kind."""


__all__ = ["HybridQCMError", "ConfigError", "DatasetError", "CheckpointError"]
