"""The errors ``cmc`` raises for input or state a user can fix; the message names the problem.

Everything here derives from :class:`CMCError`, which derives from ValueError so that callers
written against the older ValueError subclasses keep working. Callers that report errors to
people (the CLI, the service's job table) catch :class:`CMCError`; anything else is a bug and
should show as one. Cancellation (``TrainingCancelled``, ``PoseEstimationCancelled``) is not an
error and is not here.
"""

from __future__ import annotations


class CMCError(ValueError):
    """Base of every user-facing ``cmc`` error."""


class SceneError(CMCError):
    """A scene (photos, scene folder) that cannot be trained on."""


class CameraError(CMCError):
    """A camera file or camera parameters that cannot be used."""


class PoseEstimationError(CMCError):
    """Poses could not be estimated from these photos; the message names the photos and a remedy."""


class BakedFormatError(CMCError):
    """A baked folder that cannot be read."""


class CheckpointError(CMCError):
    """A training checkpoint of another version or another training configuration."""


class ConfigError(CMCError):
    """A preset, setting or command option that cannot be used."""
