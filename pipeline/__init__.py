"""The orchestrator: stage API, content-addressed workspace, DAG, runner, CLI.

This package knows nothing about faces. It finds stages by module name from
``configs/pipeline.yaml`` and never imports ``stages``, ``scene``, ``avatar`` or
``hardware`` directly.
"""

from pipeline.errors import PipelineError, ConfigError, StageFailed
from pipeline.stage import Stage, StageContext, StageParams

__all__ = ["PipelineError", "ConfigError", "StageFailed", "Stage", "StageContext", "StageParams"]
