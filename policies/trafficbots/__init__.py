"""TrafficBots V1.5 re-implementation: network, closed-loop rollout, losses, checkpoints."""

from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.checkpoint import (
    average_checkpoints,
    load_checkpoint,
    load_state_into,
    save_checkpoint,
)
from policies.trafficbots.config import InferenceConfig, TrafficBotsConfig
from policies.trafficbots.inference import RolloutSamples, sample_rollouts
from policies.trafficbots.losses import LossConfig, training_step
from policies.trafficbots.model import RolloutContext, RolloutState, StepOutput, TrafficBots
from policies.trafficbots.rollout import Trajectory, rollout

__all__ = [
    "InferenceConfig",
    "LossConfig",
    "RolloutContext",
    "RolloutSamples",
    "RolloutState",
    "StepOutput",
    "TokenBatch",
    "TrafficBots",
    "TrafficBotsConfig",
    "Trajectory",
    "average_checkpoints",
    "load_checkpoint",
    "load_state_into",
    "rollout",
    "sample_rollouts",
    "save_checkpoint",
    "training_step",
]
