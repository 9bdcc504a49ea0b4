"""`safesysid compare`: the Table III cell (collide / fail at N lb / success), the dumbbell and
method lists, and a tiny compare end to end (tables, run folders, figures, resume)."""

import csv
import json
import re

import pytest
from safesysid.cli import BadInput, main
from safesysid.compare_cli import cell, parse_dumbbells, parse_methods, stack_layer, table
from safesysid.scenario import SCENARIOS_DIR
from safesysid.systems.config import METHODS

CATALOGUE = {"4lb": 1.814, "5lb": 2.268, "6lb": 2.722, "7lb": 3.175, "8lb": 3.629}
ALL = list(CATALOGUE)
CELL = re.compile(r"^(success|collide|fail at \d+lb)$")


def run(dumbbell, success=True, failure=None, collisions=0, method="m", trial=0):
    return dict(method=method, dumbbell=dumbbell, trial=trial, success=success, failure=failure, collisions=collisions)


def test_cell_success_only_when_every_run_of_every_dumbbell_succeeded():
    runs = [run(d, trial=k) for d in ALL for k in range(3)]
    assert cell(runs, ALL, expected=15) == "success"
    runs[-1] = run("8lb", False, "placement", trial=2)  # one trial of five dumbbells x three
    assert cell(runs, ALL, expected=15) == "fail at 8lb"


def test_cell_names_the_lightest_failing_dumbbell_whatever_the_order():
    runs = [run("8lb", False, "torque_limit"), run("4lb"), run("6lb", False, "tracking"), run("5lb"), run("7lb")]
    assert cell(runs, ALL, expected=5) == "fail at 6lb"
    runs[1] = run("4lb", False, "placement")
    assert cell(runs, ALL, expected=5) == "fail at 4lb"


def test_cell_a_collision_anywhere_ranks_above_a_failure():
    runs = [run("4lb", False, "torque_limit"), run("5lb"), run("6lb"), run("7lb"), run("8lb", False, "collision", 2)]
    assert cell(runs, ALL, expected=5) == "collide"
    # counted on the referee's collision count too, even when another failure came first
    runs[-1] = run("8lb", False, "torque_limit", collisions=1)
    assert cell(runs, ALL, expected=5) == "collide"


def test_cell_of_an_interrupted_compare_does_not_claim_success():
    runs = [run("4lb"), run("5lb")]
    assert cell(runs, ALL, expected=5).startswith("incomplete (2/5")
    assert cell(runs + [run("6lb", False, "tracking")], ALL, expected=5) == "fail at 6lb"


def test_table_counts_per_dumbbell():
    done = [run("4lb", method="ours"), run("4lb", False, "placement", method="wrong"), run("6lb", method="wrong")]
    rows = table(done, ["ours", "wrong"], ["4lb", "6lb"], trials=1)
    assert rows["wrong"]["cell"] == "fail at 4lb"
    assert rows["wrong"]["per_dumbbell"]["4lb"] == {"runs": 1, "success": 0, "failures": {"placement": 1}}
    assert rows["ours"]["cell"].startswith("incomplete (1/2")


def test_dumbbell_and_method_lists():
    assert parse_dumbbells("4lb..8lb", CATALOGUE, "4lb") == ALL
    assert parse_dumbbells("7lb..5lb", CATALOGUE, "4lb") == ["5lb", "6lb", "7lb"]
    assert parse_dumbbells("8lb,4lb,8lb", CATALOGUE, "4lb") == ["4lb", "8lb"]  # lightest first, once
    assert parse_dumbbells(None, CATALOGUE, "6lb") == ["6lb"]
    for bad in ("4lb..9lb", "4lb,3kg"):
        with pytest.raises(BadInput, match="--dumbbells"):
            parse_dumbbells(bad, CATALOGUE, "4lb")
    assert parse_methods("all") == list(METHODS)
    assert parse_methods("wrong, ours") == ["wrong", "ours"]
    with pytest.raises(BadInput, match="--methods"):
        parse_methods("ours,best")


# A short identification (one 1-s plan) keeps the four runs of the tiny compare quick.
SHORT = "planner: {num_plans: 1, duration_s: 1.0, replan_period_s: 0.5}"


def test_tiny_compare_writes_table_iii_cells_run_folders_and_resumes(tmp_path, capsys):
    out = tmp_path / "cmp"
    args = ["compare", str(SCENARIOS_DIR / "quickstart.yaml"), "--methods", "ours,wrong", "--dumbbells", "8lb,4lb"]
    args += ["--trials", "1", "--workers", "2", "--out", str(out), "--scenario-text", SHORT]
    assert main(args) == 0
    runs = [json.loads(line) for line in (out / "runs.jsonl").read_text().splitlines()]
    assert sorted((s["method"], s["dumbbell"]) for s in runs) == [
        ("ours", "4lb"),
        ("ours", "8lb"),
        ("wrong", "4lb"),
        ("wrong", "8lb"),
    ]
    for s in runs:
        assert (out / s["method"] / s["dumbbell"] / "trial0" / "summary.json").exists()
    with (out / "table.csv").open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["method", "quickstart", "4lb", "8lb"]
    cells = {r[0]: r[1] for r in rows[1:]}
    assert set(cells) == {"ours", "wrong"}
    for method, text in cells.items():
        assert CELL.match(text), text
        mine = {s["dumbbell"]: s for s in runs if s["method"] == method}
        # the referee of the cell, written out: collision first, then the lightest failure
        if any(s["collisions"] > 0 for s in mine.values()):
            expected = "collide"
        else:
            expected = next((f"fail at {d}" for d in ("4lb", "8lb") if not mine[d]["success"]), "success")
        assert text == expected
    # wrong (no payload in the model, zero-width interval) cannot hold the 8 lb payload: the cell must say so
    assert cells["wrong"] != "success"
    md = (out / "table.md").read_text()
    assert f"| ours | {cells['ours']} |" in md and f"| wrong | {cells['wrong']} |" in md
    doc = json.loads((out / "table.json").read_text())
    assert doc["dumbbells"] == ["4lb", "8lb"] and doc["methods"]["wrong"]["cell"] == cells["wrong"]
    for name in ("table.png", "fig5_intervals.png", "fig6_mass.png", "fig8_task_ours.png", "fig8_task_wrong.png"):
        assert (out / name).stat().st_size > 5000, name
    capsys.readouterr()
    with (out / "runs.jsonl").open("a") as fh:
        fh.write('{"method": "ours", "dumbbell": "4lb", "tri')  # a line cut by a kill
    assert main(args) == 0  # resumes: the cut line dropped, nothing left to run, same table
    assert "4 runs already" in capsys.readouterr().err and len((out / "runs.jsonl").read_text().splitlines()) == 4
    assert main([*args[:-2], "--scenario-text", "seed: 3"]) == 2  # another setup in the same folder: refused


def test_compare_bad_input_exits_2(tmp_path, capsys):
    quick = str(SCENARIOS_DIR / "quickstart.yaml")
    assert main(["compare", quick, "--dumbbells", "4lb..9lb", "--out", str(tmp_path)]) == 2
    assert "--dumbbells" in capsys.readouterr().err
    assert main(["compare", quick, "--methods", "ours,best", "--out", str(tmp_path)]) == 2


def test_stack_places_each_dumbbell_on_the_lighter_ones_of_the_list():
    names = ["4lb", "5lb", "6lb"]
    assert [stack_layer(names, d, True) for d in names] == [
        [],
        ["task: {stack_on: [4lb]}"],
        ["task: {stack_on: [4lb, 5lb]}"],
    ]
    assert stack_layer(names, "6lb", False) == []
