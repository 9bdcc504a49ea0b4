"""Mutation pass over the lines docs/guarantees.md names: break each, run the tests that should see it.

    python tools/mutants.py                 # every mutant, on a copy of HEAD; prints the table
    python tools/mutants.py --only 3,7      # some of them
    python tools/mutants.py --list          # the mutants, without running anything

Each mutant replaces one snippet (which must occur exactly once) of one file and runs the named
tests (short, targeted `-k` selections); it is killed when they fail. A mutant marked `equivalent`
changes no behaviour: it is expected to survive, and the reason is printed.

The working tree is never touched (other people edit it): the committed tree at --rev is exported
with `git archive` into a temporary directory, and pytest runs there with this interpreter (the
project's venv). The venv's editable install maps `safesysid.*` onto the working tree, so the copy
gets its own import path: an alias directory whose `safesysid/` holds symlinks to the copy's app/
files and its systems/, models/, scenarios/, benchmarks/ folders (pyproject's package-dir),
put first on PYTHONPATH (a PYTHONPATH entry precedes the editable install's .pth entry). Before
each mutant the copy's file is checked against the committed text (a dirty file is refused), and
it is restored in a `finally` and checked again.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib


@dataclasses.dataclass(frozen=True)
class Mutant:
    what: str  # the mutation, in words
    path: str  # file, relative to the repository
    where: str  # the function it breaks
    original: str
    mutated: str
    tests: tuple[str, ...]  # pytest arguments: files / node ids, "-k", expressions
    equivalent: str = ""  # non-empty: changes no behaviour, and why


def m(what, path, where, original, mutated, *tests, equivalent=""):
    return Mutant(what, path, where, original, mutated, tuple(tests), equivalent)


PLANNER_SYSTEM = "systems/planner/system.py"
PLANNER = "systems/planner/safe_planner.py"
PROBLEM = "systems/planner/problem.py"
ARMOUR = "systems/controller/armour.py"
TCERT = "systems/planner/torque_certificate.py"
REACH = "systems/planner/reachability.py"
SEGMENTS = "systems/estimation/segments.py"
ENCLOSURE = "systems/estimation/enclosure.py"
INCREMENTAL = "systems/estimation/incremental.py"
T_PS = "tests/test_planner_system.py"
T_PLANNER = "tests/test_planner.py"
T_CTRL = "tests/test_controller.py"
T_REACH = "tests/test_reachability.py"
T_AFF = "tests/test_reachability_affine.py"
T_EST = "tests/test_estimator.py"
QCERT = "systems/estimation/quadrature_certificate.py"
T_QCERT = "tests/test_quadrature_certificate.py"
ACCEL = "systems/estimation/acceleration_bound.py"
T_ACCEL = "tests/test_acceleration_bound.py"

MUTANTS = [
    # -- 1. tracking tube ------------------------------------------------------------------------
    m(
        "σ_min 1.5× the certified lower bound",
        ARMOUR,
        "mass_matrix_lower_bound",
        "    return float(np.min(ia))",
        "    return float(1.5 * np.min(ia))",
        T_CTRL,
        "-k",
        "sigma_min_certified",
    ),
    m(
        "robust input 5 % too weak",
        ARMOUR,
        "robust_input",
        "lam = max(0.0, -alpha * h / norm_r + float(np.sqrt(w_bar @ w_bar)) * _UP)",
        "lam = max(0.0, -alpha * h / norm_r + 0.95 * float(np.sqrt(w_bar @ w_bar)) * _UP)",
        T_CTRL,
        "-k",
        "robust_input_hand_cases or robust_gain_on_the_tube_boundary",
    ),
    m(
        "ultimate bound ε from V_max/σ_min (factor 2 dropped)",
        ARMOUR,
        "ultimate_bound",
        "np.sqrt(2 * V_max / sigma_min)",
        "np.sqrt(V_max / sigma_min)",
        T_CTRL,
        "-k",
        "tracking_bounds_formulas",
    ),
    # -- floating point --------------------------------------------------------------------------
    m(
        "dot_rounding 0 (only the one-ulp outward rounding left)",
        "systems/math/intervals.py",
        "dot_rounding",
        "    return (k + 2) * np.finfo(float).eps",
        "    return 0 * np.finfo(float).eps",
        "tests/test_intervals.py",
        "-k",
        "rational_arithmetic",
    ),
    m(
        "LP bound pad relative to the reduced costs only (the former 1e-12)",
        ENCLOSURE,
        "certified_lp_min (_lp_bound_rounding)",
        "return max(1e-12 * terms, dot_rounding(len(r) + m) * terms + r_error) + 1e-300",
        "return 1e-12 * terms + 1e-300",
        "tests/test_rounding.py",
        "-k",
        "lp_bound_pad",
    ),
    m(
        "collision test without outward rounding (vals >= 0)",
        PROBLEM,
        "PlanningProblem.is_feasible",
        "return bool(np.all(vals >= self.clearance_rounding(pts)))",
        "return bool(np.all(vals >= 0))",
        T_PLANNER,
        "-k",
        "within_its_rounding",
    ),
    # -- 2. torque limits ------------------------------------------------------------------------
    m(
        "interval torque bound: ‖w̄‖ halved",
        TCERT,
        "torque_bound",
        "    wbar = _up((wp.mag @ d) * (1 + 1e-12))",
        "    wbar = _up(0.5 * (wp.mag @ d))",
        T_REACH,
        "-k",
        "torque_bound_covers_the_controller_command",
    ),
    m(
        "affine torque bound: ‖w̄‖ halved",
        TCERT,
        "affine_torque_bound",
        "    wbar = _up((linear + free + err) * (1 + 1e-12))",
        "    wbar = _up(0.5 * (linear + free + err))",
        T_AFF,
        "-k",
        "affine_torque_bound_covers",
    ),
    m(
        "the barrier excess (α/2)εμ_j dropped from the torque bound",
        TCERT,
        "robust_term",
        "(1 + 1e-12))[:, None] + excess)",
        "(1 + 1e-12))[:, None] + 0 * excess)",
        T_REACH,
        "-k",
        "torque_bound_covers_the_controller_command",
    ),
    m(
        "error-filter gain κ 30 % too small",
        "systems/planner/affine_forms.py",
        "filter_gain",
        "            return float(total * (1 + 1e-12))",
        "            return float(0.7 * total)",
        T_AFF,
        "-k",
        "filter_gain",
    ),
    m(
        "the refined point's own certificate skipped (feasible_start)",
        PLANNER,
        "SafePlanner._refine",
        "            point = self.problem(*box, mode=mode, past=past, k_box=(target, target), shrink_toward=base)\n"
        "            if not point.feasible_start:\n                return None\n",
        "            point = self.problem(*box, mode=mode, past=past, k_box=(target, target), shrink_toward=base)\n",
        T_PLANNER,
        "-k",
        "never_adopts",
    ),
    m(
        "the refined point's collision re-check skipped (is_feasible)",
        PLANNER,
        "SafePlanner._refine",
        "            k = point.k_lo.copy()\n            if not point.is_feasible(k):\n                return None\n",
        "            k = point.k_lo.copy()\n",
        T_PLANNER,
        "-k",
        "never_adopts",
        equivalent="a point box (k, k) has no k-motion, so PlanningProblem._check_start already fails "
        "feasible_start on every pair with sd < need, the very pairs is_feasible(k) would reject",
    ),
    m(
        "the referee judges the torque after saturation",
        "systems/plant/safety_monitor.py",
        "SafetyMonitor (commanded ratio)",
        "float(np.max(np.abs(self.command_port.Eval(context)) / jp.torque_limit)),",
        "float(np.max(np.abs(u) / jp.torque_limit)),",
        "tests/test_safety_monitor.py",
        "-k",
        "before_saturation",
    ),
    # -- 3. joint limits -------------------------------------------------------------------------
    m(
        "limit box without the tube's position margin",
        REACH,
        "PlanReach.limit_box",
        "                joint_params.position_lower + self.bounds.position,",
        "                joint_params.position_lower,",
        T_REACH,
        "-k",
        "limit_box_keeps",
    ),
    m(
        "limit box without the tube's velocity margin",
        REACH,
        "PlanReach.limit_box",
        "                -joint_params.velocity_limit + self.bounds.velocity,",
        "                -joint_params.velocity_limit,",
        T_REACH,
        "-k",
        "limit_box_keeps",
    ),
    # -- 4. collisions ---------------------------------------------------------------------------
    m(
        "sphere spread over the time interval dropped",
        REACH,
        "local_spread",
        '    return _up(_up(np.einsum("nsj,nj->ns", local, rho)) * (1 + 1e-12))',
        '    return 0.0 * _up(_up(np.einsum("nsj,nj->ns", local, rho)) * (1 + 1e-12))',
        T_REACH,
        "-k",
        "local_spread_bounds",
    ),
    m(
        "collision constraint on sphere centres (radius + spread dropped)",
        PROBLEM,
        "PlanningProblem.collision",
        "        vals = vals - self.pair_need\n",
        "        vals = vals - 0 * self.pair_need\n",
        T_PLANNER,
        "-k",
        "colliding_plan_is_rejected or planned_and_random",
    ),
    # -- 5. containment --------------------------------------------------------------------------
    m(
        "quadrature bound × 0",
        SEGMENTS,
        "quadrature_bound",
        "        out[s] = c * safety * (h2[a:b] @ ",
        "        out[s] = 0 * c * safety * (h2[a:b] @ ",
        "tests/test_quadrature_containment.py",
        "-k",
        "keeps_the_truth",
    ),
    m(
        "quadrature safety κ halved (below the 2 a monotone step needs)",
        SEGMENTS,
        "quadrature_bound",
        "        out[s] = c * safety * (h2[a:b] @ ",
        "        out[s] = c * (safety / 2) * (h2[a:b] @ ",
        T_EST,
        "tests/test_quadrature_containment.py",
        "-k",
        "quadrature_bound_covers or keeps_the_truth or attained",
    ),
    m(
        "torque radius without the declared floor",
        "systems/model/torque_noise.py",
        "DeclaredTorqueNoise.bound (the estimator's torque_radius)",
        "        return self.ratio * np.abs(tau) + self.floor_Nm",
        "        return self.ratio * np.abs(tau)",
        "tests/test_estimator_adversarial.py",
        "-k",
        "truth_inside and 0",
    ),
    m(
        "θ_r's share of the enclosure radius dropped",
        ENCLOSURE,
        "linear_hull",
        "    rad_theta_r = np.abs(L @ Dr2) @ rad_r",
        "    rad_theta_r = 0 * (np.abs(L @ Dr2) @ rad_r)",
        "tests/test_estimator_adversarial.py",
        "-k",
        "truth_inside and 0",
    ),
    m(
        "the prior not intersected",
        INCREMENTAL,
        "IncrementalEstimator.update (_update_box)",
        "            lo, hi = np.maximum(lo, self.prior[0]), np.minimum(hi, self.prior[1])",
        "            lo, hi = lo, hi",
        "tests/test_estimator_prior.py",
        "-k",
        "no_published_interval_is_wider",
    ),
    m(
        "an inconsistent update does not latch",
        INCREMENTAL,
        "IncrementalEstimator.update",
        "            self.consistent = False\n        self.messages.extend(notes)",
        "        self.messages.extend(notes)",
        T_EST,
        "-k",
        "inconsistent_data_keep_the_last",
    ),
    # -- 6. plans run with the parameters they were certified with -------------------------------
    m(
        "a failed plan switches the controller to the new estimate",
        PLANNER_SYSTEM,
        "ExcitingPlanner._plan_into",
        '            new.events = st.events + self._stop_events(st, t, "plan_failed", f"{res.status}: {res.reason}")\n',
        '            new.events = st.events + self._stop_events(st, t, "plan_failed", f"{res.status}: {res.reason}")\n'
        "            new.thetas = thetas\n",
        T_PS,
        "-k",
        "never_switches",
    ),
    m(
        "holding q0 with the parameters of a failed first call",
        PLANNER_SYSTEM,
        "ExcitingPlanner._plan_into",
        '            new.events = st.events + self._stop_events(st, t, "plan_failed", f"{res.status}: {res.reason}")\n',
        '            new.events = st.events + self._stop_events(st, t, "plan_failed", f"{res.status}: {res.reason}")\n'
        "            if st.plan is None:\n                new.thetas = thetas\n",
        T_PS,
        "-k",
        "never_switches",
    ),
    m(
        "a certified plan keeps the previous plan's parameters",
        PLANNER_SYSTEM,
        "ExcitingPlanner._plan_into",
        "            new.plan, new.t_start, new.thetas = res, t, thetas",
        "            new.plan, new.t_start = res, t",
        T_PS,
        "-k",
        "outputs_the_parameters",
    ),
    m(
        "an inconsistent estimate is planned with",
        PLANNER_SYSTEM,
        "ExcitingPlanner._plan_into",
        "        if not self._estimate_consistent(context):",
        "        if False:",
        T_PS,
        "-k",
        "inconsistent_estimate_is_never",
    ),
    # -- 7. end to end ---------------------------------------------------------------------------
    m(
        "a failed plan does not end the loop",
        PLANNER_SYSTEM,
        "ExcitingPlanner._plan_into",
        "        new.done = (not res.ok) or calls >= self._num_plans",
        "        new.done = calls >= self._num_plans",
        T_PS,
        "-k",
        "failed_plan_keeps",
    ),
    m(
        "a control step above 1 ms accepted (A6)",
        "app/scenario.py",
        "validate",
        "        0 < s.plant.time_step_s <= MAX_CONTROL_STEP_S,",
        "        0 < s.plant.time_step_s,",
        "tests/test_scenario.py",
        "-k",
        "bad_keys",
    ),
    # -- 5. A5 certified from an acceleration bound ------------------------------------------------
    m(
        "quadrature certificate: the step's boxes without the acceleration widening",
        QCERT,
        "step_boxes",
        "    a = np.asarray(accel, float)[:, None, :]",
        "    a = 0 * np.asarray(accel, float)[:, None, :]",
        T_QCERT,
        "-k",
        "boxes_hold",
    ),
    m(
        "quadrature certificate × 0",
        QCERT,
        "certified_step_bounds",
        "    bound = _up(h / substeps * _up(",
        "    bound = 0 * _up(h / substeps * _up(",
        T_QCERT,
        "-k",
        "oscillation_between_samples",
    ),
    m(
        "an acceleration bound the samples contradict does not latch consistent off",
        INCREMENTAL,
        "IncrementalEstimator._update_box",
        "        if np.any(self.rows.accel_violated):",
        "        if False:",
        T_QCERT,
        "-k",
        "contradicted_bound_latches",
    ),
    m(
        "over LCM, the task's curves start at the switch, not when the worker's result is back",
        "systems/hardware/task_source.py",
        "WallClockTaskSource._poll",
        "        curves, start = [], t  # the arm held at q_switch until now: the curves start here",
        "        curves, start = [], t_switch",
        "tests/test_hardware_task.py",
        "-k",
        "wall_clock_task",
    ),
    m(
        "over LCM, an unconfirmed release is taken for a release (the controller drops the payload)",
        "app/task_lcm.py",
        "_release",
        '    if verdict == "open":',
        '    if verdict in ("open", "lost"):',
        "tests/test_hardware_task.py",
        "-k",
        "never_confirmed and gripper_command",
    ),
    m(
        "arm-sim's gripper ignores the open command",
        "app/arm_gripper.py",
        "ArmGripper.step",
        "        if self.t_release is None and self.server.open_requested():",
        "        if False:",
        "tests/test_hardware_task.py",
        "-k",
        "open_command_releases",
    ),
    m(
        "the Meshcat view of an arm over LCM ignores the received positions",
        "app/lcm_view.py",
        "StatusView._publish",
        "        self.plant.SetPositions(plant_context, q)",
        "        self.plant.SetPositions(plant_context, 0 * q)",
        "tests/test_hardware_task.py",
        "-k",
        "meshcat",
    ),
    m(
        "the referee after the run judges every sample on one pose (the sample's state not set)",
        "systems/plant/safety_monitor.py",
        "judge_log",
        '        arm.plant.SetPositionsAndVelocities(plant_context, arm.instance, log["state"][i])',
        "        pass",
        "tests/test_safety_monitor.py",
        "-k",
        "judging_the_log",
    ),
    m(
        "over LCM, a message older than the last accepted one is taken (statuses out of order)",
        "systems/hardware/freshness.py",
        "Freshness.step",
        "            if self.armed and sent_s <= self.last_sent_s:",
        "            if False:",
        "tests/test_hardware.py",
        "-k",
        "late_and_duplicated_statuses",
    ),
    # -- 5. A5 certified from the dynamics (the derived acceleration bound) ------------------------
    m(
        "derived acceleration bound: M bounded below by the armature's upper end (a λ_max-side bound)",
        ACCEL,
        "armature_lower",
        "    ia = _down(centre - radius)",
        "    ia = _up(centre + radius)",
        T_ACCEL,
        "-k",
        "tight_on_one_joint",
    ),
    m(
        "derived acceleration bound: h(q, q̇) without the friction columns",
        ACCEL,
        "residual_bound",
        "    mid, mag = w.mid, w.mag",
        "    w.lo[..., 10 * robot.n :] = w.hi[..., 10 * robot.n :] = 0.0\n    mid, mag = w.mid, w.mag",
        T_ACCEL,
        "-k",
        "tight_on_one_joint",
    ),
    m(
        "derived acceleration bound: M⁻¹'s Cauchy–Schwarz factor 1/√Ia_j taken as 1/Ia_j",
        ACCEL,
        "from_residual",
        "    return _up(np.sqrt(energy / ia) * (1 + _REL))",
        "    return _up(np.sqrt(energy) / ia * (1 + _REL))",
        T_ACCEL,
        "-k",
        "holds_the_model_acceleration",
    ),
    m(
        "a known motion faster than the acceleration bound is not flagged",
        QCERT,
        "certify_rows",
        "    contradicted = (contradicted & ~open_) | (False if exceeded is None else exceeded)",
        "    contradicted = contradicted & ~open_",
        T_ACCEL,
        "-k",
        "known_motion_faster",
    ),
    m(
        "a step without an acceleration bound certifies its segment",
        QCERT,
        "certify_rows",
        "a5_certified=~(bad | unbounded)",
        "a5_certified=~bad",
        T_ACCEL,
        "-k",
        "without_a_bound",
    ),
    # -- diagnosis: only what every equally good set shares is named (guarantees.md row 44) --------
    m(
        "the diagnosis names the best set's effects that an equally good set lacks",
        "systems/diagnosis/selection.py",
        "select_effects",
        "        selected = [e for e in selected if e not in unresolved]",
        "        selected = list(selected)",
        "tests/test_diagnosis_uncertainty.py",
        "-k",
        "rival_within_one_standard_error",
    ),
    # -- guarantee 6 in wall-clock time: a plan computed one period ahead (guarantees.md row 45) ---
    m(
        "a wall-clock plan executes with the estimate at its start, not the one it was certified with",
        "systems/hardware/background.py",
        "_PlanAhead._collect",
        "        return replace(res, thetas=thetas)  # certified with the estimate of its submission",
        "        return res",
        T_PS,
        "-k",
        "wall_clock_plan_executes",
    ),
    # -- the controller beside the arm: the arm takes only an early, continuous plan (rows 46-47) ---
    m(
        "the arm takes a plan that arrives after its start",
        "systems/hardware/plan_follower.py",
        "PlanFollower._offer",
        "        if start <= t:",
        "        if False:",
        "tests/test_plan_link.py",
        "-k",
        "only_new_early_and_continuous",
    ),
    m(
        "the arm takes a plan that does not start where the executing trajectory is",
        "systems/hardware/plan_follower.py",
        "PlanFollower._offer",
        "        if not all(",
        "        if False and not all(",
        "tests/test_plan_link.py",
        "-k",
        "only_new_early_and_continuous",
    ),
    # -- the task beside the arm: the release at rest at the task's end, then the bare end effector (rows 48-51)
    m(
        "the gripper may open before the arm has reached the end of the task trajectory",
        "systems/hardware/plan_follower.py",
        "PlanFollower.release_refusal",
        "        if context.get_time() < plan.piece.t_end:",
        "        if False:",
        "tests/test_plan_link.py",
        "-k",
        "lets_the_payload_go_only_at_its_end",
    ),
    m(
        "the controller keeps the payload's parameters after the release",
        "systems/hardware/plan_follower.py",
        "PlanFollower._thetas",
        "        if st.released and self.released is not None:",
        "        if False:",
        "tests/test_plan_link.py",
        "-k",
        "lets_the_payload_go_only_at_its_end",
    ),
    m(
        "the arm takes a task curve that is not at rest at its end",
        "systems/hardware/plan_message.py",
        "_parse_task_curve",
        "    if max(np.abs(v).max(), np.abs(a).max()) > REST_TOLERANCE:",
        "    if False:",
        "tests/test_plan_link.py",
        "-k",
        "not_at_rest_at_its_end",
    ),
    m(
        "every task curve is marked as the release plan (the payload could go at the return move's end)",
        "systems/hardware/plan_sender.py",
        "PlanSender._add_task",
        "            self._queue(timed.t_start, Plan(piece, st.thetas, release=k == len(st.curves) - 1), t)",
        "            self._queue(timed.t_start, Plan(piece, st.thetas, release=True), t)",
        "tests/test_plan_link.py",
        "-k",
        "last_one_marked_release",
    ),
]


def git(repo, *args):
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True).stdout


def export(repo: Path, rev: str, dest: Path) -> Path:
    """The committed tree at rev, as files under dest/tree (git archive: the repository is only read)."""
    tree = dest / "tree"
    tree.mkdir(parents=True)
    archive = subprocess.Popen(["git", "-C", str(repo), "archive", rev], stdout=subprocess.PIPE)
    subprocess.run(["tar", "-x", "-C", str(tree)], stdin=archive.stdout, check=True)
    if archive.wait() != 0:
        raise SystemExit(f"git archive {rev} failed")
    return tree


def alias_dir(tree: Path, dest: Path) -> Path:
    """dest/alias/safesysid/...: symlinks mapping the package names onto the copy (pyproject's package-dir)."""
    mapping = tomllib.loads((tree / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    root = dest / "alias"
    top = root / "safesysid"
    top.mkdir(parents=True)
    subpackages = {name.split(".", 1)[1]: folder for name, folder in mapping.items() if "." in name}
    for entry in (tree / mapping["safesysid"]).iterdir():
        if entry.name not in subpackages:
            (top / entry.name).symlink_to(entry)
    for name, folder in subpackages.items():
        (top / name).symlink_to(tree / folder, target_is_directory=True)
    return root


def run_tests(tree: Path, alias: Path, tests, timeout_s: float) -> tuple[str, float]:
    env = {**os.environ, "PYTHONPATH": str(alias), "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("SAFESYSID_FULL", None)
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests]
    start = time.perf_counter()
    try:
        done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return "timeout", time.perf_counter() - start
    code = {0: "passed", 1: "failed", 5: "no tests"}.get(done.returncode, f"error {done.returncode}")
    return code, time.perf_counter() - start


def run_mutant(mutant: Mutant, tree: Path, alias: Path, pristine: str, timeout_s: float) -> tuple[str, float]:
    """Apply, run, restore (always). Returns (result, seconds)."""
    target = tree / mutant.path
    if target.read_text() != pristine:
        raise SystemExit(f"{mutant.path} differs from the committed text: refusing to mutate a dirty file")
    if pristine.count(mutant.original) != 1:
        return "stale (snippet not found once)", 0.0
    try:
        target.write_text(pristine.replace(mutant.original, mutant.mutated))
        outcome, seconds = run_tests(tree, alias, mutant.tests, timeout_s)
    finally:
        target.write_text(pristine)
    if target.read_text() != pristine:
        raise SystemExit(f"{mutant.path} was not restored")
    killed = outcome in ("failed", "timeout") or outcome.startswith("error")
    if mutant.equivalent:
        return ("survived (equivalent)" if outcome == "passed" else f"killed ({outcome}) although equivalent"), seconds
    return (f"killed ({outcome})" if killed else f"SURVIVED ({outcome})"), seconds


def patched(patches) -> set[str]:
    """Paths the --patch diffs change."""
    return {
        line[6:].strip() for patch in patches for line in patch.read_text().splitlines() if line.startswith("+++ b/")
    }


def table(rows) -> str:
    lines = ["| # | mutation | file: function | killing test | result |", "|---|---|---|---|---|"]
    for index, mutant, result in rows:
        tests = " ".join(mutant.tests).replace("|", "\\|")
        why = f" — {mutant.equivalent}" if mutant.equivalent else ""
        lines.append(f"| {index} | {mutant.what}{why} | `{mutant.path}`: {mutant.where} | `{tests}` | {result} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repo", type=Path, default=Path(__file__).resolve().parents[1])
    parser.add_argument("--rev", default="HEAD")
    parser.add_argument("--only", default="", help="comma-separated mutant numbers (1-based)")
    parser.add_argument("--list", action="store_true", help="print the mutants and exit")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per test run")
    parser.add_argument("--no-baseline", action="store_true", help="skip checking the tests pass unmutated")
    parser.add_argument(
        "--patch",
        type=Path,
        action="append",
        default=[],
        help="a diff applied to the copy first (a rev that does not import, e.g. a commit that missed a hunk); "
        "the mutated files are then checked against the patched text",
    )
    args = parser.parse_args(argv)
    chosen = [int(x) for x in args.only.split(",") if x] or list(range(1, len(MUTANTS) + 1))
    if args.list:
        print(table([(i, MUTANTS[i - 1], "") for i in chosen]))
        return 0
    with tempfile.TemporaryDirectory(prefix="safesysid-mutants-") as tmp:
        dest = Path(tmp)
        tree = export(args.repo, args.rev, dest)
        for patch in args.patch:
            subprocess.run(["git", "apply", str(patch.resolve())], cwd=tree, check=True)
        alias = alias_dir(tree, dest)
        commit = git(args.repo, "rev-parse", "--short", args.rev).decode().strip()
        print(f"mutants on {commit} in {tree}", flush=True)
        if not args.no_baseline:
            for tests in dict.fromkeys(MUTANTS[i - 1].tests for i in chosen):
                outcome, seconds = run_tests(tree, alias, tests, args.timeout)
                print(f"baseline {' '.join(tests)}: {outcome} ({seconds:.0f} s)", flush=True)
                if outcome != "passed":
                    raise SystemExit("a killing test fails unmutated: fix that first")
        rows = []
        for i in chosen:
            mutant = MUTANTS[i - 1]
            pristine = git(args.repo, "show", f"{args.rev}:{mutant.path}").decode()
            if args.patch:  # the committed text as patched
                pristine = (tree / mutant.path).read_text() if mutant.path in patched(args.patch) else pristine
            result, seconds = run_mutant(mutant, tree, alias, pristine, args.timeout)
            print(f"{i:2d} {result} ({seconds:.0f} s): {mutant.what}", flush=True)
            rows.append((i, mutant, result))
    print(table(rows))
    survivors = [i for i, mutant, result in rows if not result.startswith(("killed", "survived (equivalent)"))]
    print(f"{len(rows)} mutants, {len(survivors)} not killed{': ' + str(survivors) if survivors else ''}")
    return 1 if survivors else 0


if __name__ == "__main__":
    sys.exit(main())
