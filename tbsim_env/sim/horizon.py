"""How far a simulation runs: the task decides, never the length of the log.

* WOSAC simulates the ``C.NUM_FUTURE`` (80) steps after the current one (``wosac_end_step``),
  whether the scene logs them (training and validation splits) or not (the test split, whose
  scenes hold only the 11 history steps).
* An RL episode (``TrafficEnv``, ``BatchedTrafficEnv``) runs from ``EnvConfig.start_step`` to
  ``EnvConfig.last_step`` (step 90 unless configured).

A simulation runs on the scenario put on its time grid (``Scenario.on_time_grid``): past the end
of the log no track has a logged state, so agents driven by a policy carry on while a
log-replayed agent would leave. What replays the log or compares with it checks first that the
log covers the horizon (``Scenario.require_log_until``), and refuses with a
``MissingFutureError`` naming the scene.
"""

from __future__ import annotations

from tbsim_env.core import constants as C
from tbsim_env.core.config import EnvConfig
from tbsim_env.core.errors import UnusableScenarioError
from tbsim_env.data.scenario import Scenario


def wosac_end_step(scenario: Scenario) -> int:
    """Last step of a WOSAC rollout: 80 steps after the current one (90 in WOMD)."""
    return scenario.current_index + C.NUM_FUTURE


def wosac_scenario(scenario: Scenario) -> Scenario:
    """``scenario`` on the time grid of a WOSAC rollout (itself for a full WOMD scene)."""
    return scenario.on_time_grid(wosac_end_step(scenario) + 1)


def episode_scenario(scenario: Scenario, config: EnvConfig, *, replays_log: bool) -> Scenario:
    """``scenario`` on the time grid of an episode (itself for a full WOMD scene by default).

    Args:
        scenario: as read.
        config: the episode's ``start_step`` and ``last_step``.
        replays_log: NPCs copy the log (``npc_policy="log_replay"``): the log must then
            cover the whole episode.

    Raises:
        MissingFutureError: the log does not reach ``start_step``, or (``replays_log``) the
            last step of the episode.
        UnusableScenarioError: the scenario's current step (``current_time_index``) is not
            ``start_step``: an episode starts at the scene's current step, with its history
            before it, so one that starts elsewhere would treat logged future as history or
            history as future.
    """
    start, end = config.start_step, config.last_step
    scenario.require_log_until(start, f"an episode that starts at step {start}")
    if scenario.current_index != start:
        raise UnusableScenarioError(
            f"its current step ('current_time_index') is {scenario.current_index}, but the "
            f"episode starts at step {start} (EnvConfig.start_step); set start_step to the "
            "current step",
            scenario.scenario_id,
            scenario.source,
        )
    if replays_log:
        scenario.require_log_until(
            end, "replaying the NPCs' log (npc_policy='log_replay') to the episode's last step"
        )
    return scenario.on_time_grid(end + 1)


__all__ = ["episode_scenario", "wosac_end_step", "wosac_scenario"]
