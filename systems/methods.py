"""The eleven methods of the paper's table of comparisons (§VII-B, tab:comparisons) as data.

Each MethodSpec says, as the table's columns do: the controller of the task phase, its robot model
(theta0) and model uncertainty ([theta]), and the identification phase before the task: which
exciting trajectory, which controller tracks it, and how the method identifies. A method without
an identification phase goes straight to the task ("N/A" in the table's last column).

Parameter sources (what the controller's theta0 / [theta] inputs carry):
  NO_PAYLOAD  the robot model file's bare end effector with zero width: "assume no payload"
  PRIOR       Table II: scenario.initial_interval on the end effector, the rest of the robot
              nominal +- noise.theta_r_ratio (systems/controller/armour.py prior_box)
  IDENTIFIED  theta0 / [theta] of Algorithm 1 (the SysIdEstimator) at the end of the excitation
  ADAPTED     the adaptive controller's own estimate: it starts at the PRIOR nominal and adapts
              inside the PRIOR box (its projection set; adap-2's robust term too), so its inputs
              carry PRIOR

uncertainty None = "N/A": the law has no use for [theta] (PID, adaptive); its box input then
carries the model's source.
"""

from __future__ import annotations

from dataclasses import dataclass

NO_PAYLOAD, PRIOR, IDENTIFIED, ADAPTED = "no_payload", "prior", "identified", "adapted"
# Trajectories of the identification phase.
EXCITING, RANDOM, FOURIER = "exciting", "random", "fourier"
# How a method identifies.
ESTIMATOR, ADAPTATION, NONE = "estimator", "adaptation", "none"
CONTROLLER_KINDS = ("armour", "pid", "adaptive", "adaptive_robust")


@dataclass(frozen=True)
class Excitation:
    """The identification phase: `trajectory` tracked by controller `controller`.

    exciting / random: Algorithm 2's receding-horizon planner (its exciting cost, or random
    feasible k as the paper's "random"); the controller takes the parameters each plan was
    certified with (the estimator's, through the planner, when the method identifies with it; the
    PRIOR otherwise). fourier: the classical Fourier trajectory (systems/excitation/fourier.py),
    no planner; the controller takes the PRIOR (identification comes after the excitation)."""

    trajectory: str
    controller: str


@dataclass(frozen=True)
class MethodSpec:
    name: str
    controller: str  # task-phase controller kind (CONTROLLER_KINDS)
    model: str  # task-phase theta0 source
    uncertainty: str | None  # task-phase [theta] source; None: N/A
    excitation: Excitation | None  # None: no identification phase
    identifies: str  # ESTIMATOR (Algorithm 1 on the excitation's data) | ADAPTATION | NONE
    row: str  # the paper's table row, for tables and reports

    def __post_init__(self):
        # The registry's own consistency (a typo in a row fails at import, not in a run).
        kinds = [self.controller] + ([self.excitation.controller] if self.excitation else [])
        consistent = (
            all(k in CONTROLLER_KINDS for k in kinds)
            and (self.model == IDENTIFIED) == (self.identifies == ESTIMATOR)
            and (self.model == ADAPTED) == (self.identifies == ADAPTATION)
            and (self.identifies != ESTIMATOR or self.excitation is not None)
        )
        if not consistent:
            raise ValueError(f"method {self.name!r}: inconsistent specification")

    @property
    def box_source(self) -> str:
        """Source of the controller's theta_lower / theta_upper inputs in the task."""
        source = self.uncertainty or self.model
        return PRIOR if source == ADAPTED else source

    @property
    def theta0_source(self) -> str:
        return PRIOR if self.model == ADAPTED else self.model

    @property
    def first_controller(self) -> str:
        """The controller the run starts with (the excitation's, else the task's)."""
        return self.excitation.controller if self.excitation else self.controller

    @property
    def switches_controller(self) -> bool:
        """The task is run by another controller than the excitation (grav-pid-ours)."""
        return self.excitation is not None and self.excitation.controller != self.controller

    @property
    def uses_planner(self) -> bool:
        return self.excitation is not None and self.excitation.trajectory in (EXCITING, RANDOM)


_ARMOUR_EXCITING = Excitation(EXCITING, "armour")
METHODS_SPEC: dict[str, MethodSpec] = {
    s.name: s
    for s in (  # name, task controller, model, uncertainty, excitation, identifies, the paper's row
        MethodSpec("ours", "armour", IDENTIFIED, IDENTIFIED, _ARMOUR_EXCITING, ESTIMATOR,
                   "ARMOUR robust | theta0 from Alg. 1 | [theta] from Alg. 1 | Alg. 2"),
        MethodSpec("wrong", "armour", NO_PAYLOAD, NO_PAYLOAD, None, NONE,
                   "ARMOUR robust | no payload | 0 % | N/A"),
        MethodSpec("conservative", "armour", PRIOR, PRIOR, None, NONE,
                   "ARMOUR robust | Table II nominal | Table II interval | N/A"),
        MethodSpec("random", "armour", IDENTIFIED, IDENTIFIED, Excitation(RANDOM, "armour"), ESTIMATOR,
                   "ARMOUR robust | theta0 from Alg. 1 | [theta] from Alg. 1 | random"),
        MethodSpec("adap-1", "adaptive", ADAPTED, None, None, ADAPTATION,
                   "adaptive (Slotine-Li) | identified by the adaptive controller | N/A | N/A"),
        MethodSpec("adap-1-excit", "adaptive", ADAPTED, None, Excitation(EXCITING, "adaptive"), ADAPTATION,
                   "adaptive (Slotine-Li) | identified by the adaptive controller | N/A | Alg. 2"),
        MethodSpec("adap-2", "adaptive_robust", ADAPTED, None, None, ADAPTATION,
                   "adaptive robust | identified by the adaptive controller | N/A | N/A"),
        MethodSpec("adap-2-excit", "adaptive_robust", ADAPTED, None, Excitation(EXCITING, "adaptive_robust"),
                   ADAPTATION, "adaptive robust | identified by the adaptive controller | N/A | Alg. 2"),
        MethodSpec("grav-pid", "pid", NO_PAYLOAD, None, None, NONE,
                   "gravity-compensated PID | no payload | N/A | N/A"),
        MethodSpec("grav-pid-ours", "pid", IDENTIFIED, None, _ARMOUR_EXCITING, ESTIMATOR,
                   "gravity-compensated PID | theta0 from Alg. 1 | N/A | Alg. 2"),
        MethodSpec("grav-pid-excit", "pid", IDENTIFIED, None, Excitation(FOURIER, "pid"), ESTIMATOR,
                   "gravity-compensated PID | theta0 from Alg. 1 | N/A | Fourier [7]"),
    )
}  # fmt: skip


def method_spec(name: str) -> MethodSpec:
    try:
        return METHODS_SPEC[name]
    except KeyError:
        raise ValueError(f"method {name!r} is not one of {', '.join(METHODS_SPEC)}") from None
