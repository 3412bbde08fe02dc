"""The streaming pipeline (ARCHITECTURE.md §1, §6, §12): stages, typed handoffs, the loop and its trust rules."""
from edge_landing.runtime.pipeline.loop import Pipeline, PipelineOptions
from edge_landing.runtime.pipeline.records import decision_record, describe_target, run_record
from edge_landing.runtime.pipeline.stages import FrameCheck, JointInference, PairInference, ScaleStage
from edge_landing.runtime.pipeline.stats import STAGES, RunSummary, StageTimes
from edge_landing.runtime.pipeline.trust import Continuity, ContinuityConfig

__all__ = ["Pipeline", "PipelineOptions", "decision_record", "describe_target", "run_record", "FrameCheck",
           "JointInference", "PairInference", "ScaleStage", "STAGES", "RunSummary", "StageTimes", "Continuity",
           "ContinuityConfig"]
