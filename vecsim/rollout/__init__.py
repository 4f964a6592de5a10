"""Training-side rollouts: :class:`EnvLoop`, the pipelined rollout of a policy over a job's
stages (:mod:`vecsim.rollout.loop`), what it answers (:mod:`vecsim.rollout.results`), its
example policy (:mod:`vecsim.rollout.policies`) and videos (:mod:`vecsim.rollout.video`), and
:class:`TaskBalancedSampler`, which draws its trajectory requests (:mod:`vecsim.rollout.sampler`);
:mod:`vecsim.rollout.intervals` holds the interval arithmetic of the rollout's timing.

    from vecsim.rollout import EnvLoop, TaskBalancedSampler
"""

from vecsim.rollout.loop import EnvLoop
from vecsim.rollout.policies import ExampleCNNPolicy
from vecsim.rollout.results import LostTrajectory, RolloutResult, RolloutStats, Trajectory
from vecsim.rollout.video import write_video
from vecsim.rollout.sampler import TaskBalancedSampler, TaskInstances, stage_of, task_ids_of

__all__ = [
    "EnvLoop",
    "ExampleCNNPolicy",
    "LostTrajectory",
    "RolloutResult",
    "RolloutStats",
    "TaskBalancedSampler",
    "TaskInstances",
    "Trajectory",
    "stage_of",
    "task_ids_of",
    "write_video",
]
