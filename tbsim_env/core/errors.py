"""Exception types of tbsim. Every message names the file, record and field at fault."""

from __future__ import annotations


class TbsimError(Exception):
    """Base class of every error raised on purpose by tbsim."""


class ScenarioFormatError(TbsimError, ValueError):
    """A scenario file or record is malformed.

    Attributes:
        path: file the record came from (or a description such as ``"<generated>"``).
        record: 0-based record index inside the file, or ``None`` for single-record formats.
        offset: byte offset of the record start inside the file, or ``None``.
        reason: what is wrong, naming the field where possible.
    """

    def __init__(
        self,
        reason: str,
        path: str | None = None,
        record: int | None = None,
        offset: int | None = None,
    ) -> None:
        self.path = path
        self.record = record
        self.offset = offset
        self.reason = reason
        where = []
        if path is not None:
            where.append(f"file {path!r}")
        if record is not None:
            where.append(f"record {record}")
        if offset is not None:
            where.append(f"byte offset {offset}")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {reason}" if prefix else reason)


class MissingFutureError(TbsimError, ValueError):
    """A task needs logged states that the scenario does not hold.

    WOSAC test-split scenes hold only the history (11 steps, current step 10): they can be
    simulated for any horizon, but log replay, scoring against the log or a training target
    need the logged future. Built by ``Scenario.require_log_until``.

    Attributes:
        scenario_id: the scenario.
        source: where it came from (file, record).
        task: what needed the log (e.g. "log replay").
        needed_step: the last step the task needs.
        logged_steps: how many steps the log holds (steps 0 .. logged_steps - 1).
    """

    def __init__(
        self,
        scenario_id: str,
        source: str,
        task: str,
        needed_step: int,
        logged_steps: int,
        current_index: int,
    ) -> None:
        self.scenario_id = scenario_id
        self.source = source
        self.task = task
        self.needed_step = needed_step
        self.logged_steps = logged_steps
        kind = (
            f"history only, current step {current_index}, as in the WOSAC test split"
            if logged_steps <= current_index + 1
            else f"current step {current_index}"
        )
        super().__init__(
            f"scenario {scenario_id} ({source}): {task} needs the logged states up to step "
            f"{needed_step}, but the log holds only steps 0-{logged_steps - 1} ({kind})"
        )


class UnusableScenarioError(TbsimError, ValueError):
    """A valid scenario cannot serve the task asked of it: an environment whose controlled
    agents are not valid at its start step, or whose start step is not the scenario's current
    step (``current_time_index``).

    Attributes:
        scenario_id: the scenario, or None when the message is about several.
        source: where it came from (file, record), or None.
        reason: what is wrong.
    """

    def __init__(
        self, reason: str, scenario_id: str | None = None, source: str | None = None
    ) -> None:
        self.scenario_id = scenario_id
        self.source = source
        self.reason = reason
        where = f"scenario {scenario_id}" if scenario_id is not None else ""
        if source is not None:
            where = f"{where} ({source})" if where else source
        super().__init__(f"{where}: {reason}" if where else reason)


class PolicyError(TbsimError, RuntimeError):
    """A policy returned something the simulation cannot use (non-finite NPC actions); the
    message names the policy and the agents."""


class ActionError(TbsimError, ValueError):
    """An action given to the environment is not usable (NaN, wrong shape, unknown agent)."""


class CheckpointError(TbsimError, ValueError):
    """A checkpoint does not match the model it is loaded into."""
