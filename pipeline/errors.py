"""Typed errors. The CLI turns each into one clear line and an exit code."""

from __future__ import annotations


class PipelineError(Exception):
    """Base of every error the pipeline reports to a user (exit code 1 unless a subclass says)."""

    exit_code = 1


class ConfigError(PipelineError):
    """A bad configuration value or bad command-line usage (exit code 2).

    The message names the file, the key and what is allowed.
    """

    exit_code = 2


class StageFailed(PipelineError):
    """A stage raised while running; the message names the stage and how to resume."""

    exit_code = 1


class InputError(PipelineError):
    """Bad input data (a file, camera, frame or key); raised by stages.

    Messages must name the offending file / camera / frame / key and say what to do.
    """

    exit_code = 1


class WorkspaceLocked(PipelineError):
    """Another ``pipeline run`` holds this workspace's lock."""

    exit_code = 1
