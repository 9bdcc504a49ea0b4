"""replay.html as a person sees it: headless Chromium renders the recording of a short run and
the arm must fill a fair share of the central frame (the camera is framed on it), with the
phases named. The arm's pixels are those that change when the arm alone is hidden, so the
check fails on a page whose camera looks away from the arm (tested) or where the arm is a
small figure far away (the replay before the camera was framed: 0.7 % of the frame; now 6.8 %).
Also what a person sees of a running `safesysid run`: Ctrl-C and the progress line."""

import base64
import json
import re
import shutil
import subprocess

import numpy as np
import pytest

ARM_PATH = "/drake/visualizer/kinova_gen3"  # the Gen3 model instance under MeshcatVisualizer's prefix
MIN_ARM_SHARE = 0.04  # of the central frame (the middle 60 % x 60 % of an 800 x 600 view)
SHORT = "planner: {num_plans: 1, duration_s: 1.0, replan_period_s: 0.5}"


def browser():
    found = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if found is None:
        pytest.skip("chromium not installed (apt-get install -y chromium)")
    return found


@pytest.fixture(scope="module")
def replay(tmp_path_factory):
    from safesysid.online import run_online
    from safesysid.scenario import SCENARIOS_DIR, load_scenario

    browser()
    out = tmp_path_factory.mktemp("replay")
    run_online(load_scenario(SCENARIOS_DIR / "quickstart.yaml", overrides=[SHORT]), out, method="ours")
    return out / "replay.html"


def meshcat_paths(page):
    """Every /drake/... path the page's embedded Meshcat commands name."""
    paths = set()
    for blob in re.findall(r'fetch\("data:application/octet-binary;base64,([^"]+)"\)', page):
        paths.update(m.decode() for m in re.findall(rb"/drake/[A-Za-z0-9_/]+", base64.b64decode(blob)))
    return paths


def with_commands(page, commands):
    """The page plus Meshcat commands applied once its own commands have been handled."""
    calls = "".join(f"viewer.handle_command({c});" for c in commands)
    return page.replace("</body>", f"<script>setTimeout(function(){{{calls}}}, 2500);</script></body>", 1)


HIDE_ARM = f'{{type: "set_property", path: "{ARM_PATH}", property: "visible", value: false}}'
LOOK_AWAY = '{type: "set_target", value: [20.0, 15.0, 22.0]}'  # three.js axes (y up): up and away from the arm


def screenshots(pages, tmp_path):
    """PNG screenshots (800 x 600) of several pages, rendered by headless Chromium in parallel."""
    procs, shots = [], []
    for k, page in enumerate(pages):
        html = tmp_path / f"page{k}.html"
        html.write_text(page)
        png = tmp_path / f"shot{k}.png"
        args = [browser(), "--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
        args += ["--hide-scrollbars", "--window-size=800,600", "--virtual-time-budget=8000"]
        args += [f"--user-data-dir={tmp_path / f'profile{k}'}", f"--screenshot={png}", html.as_uri()]
        procs.append(subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        shots.append(png)
    for proc in procs:
        proc.wait(timeout=180)
    from matplotlib.image import imread

    return [imread(png)[:, :, :3] for png in shots]


def arm_share(shown, hidden, change=0.1):
    """Share of the central frame's pixels that the arm changes (hidden vs shown, any channel)."""
    h, w = shown.shape[:2]
    centre = (slice(int(0.2 * h), int(0.8 * h)), slice(int(0.2 * w), int(0.8 * w)))
    differs = np.abs(shown[centre] - hidden[centre]).max(axis=2) > change
    return float(differs.mean())


def test_replay_shows_the_arm_framed_in_the_centre(replay, tmp_path):
    page = replay.read_text()
    assert any(p.startswith(ARM_PATH + "/") for p in meshcat_paths(page))  # else hiding it would test nothing
    shown, hidden, away, away_hidden = screenshots(
        [
            page,
            with_commands(page, [HIDE_ARM]),
            with_commands(page, [LOOK_AWAY]),
            with_commands(page, [LOOK_AWAY, HIDE_ARM]),
        ],
        tmp_path,
    )
    assert shown.std() > 0.02, "blank page: the recording did not render"
    share = arm_share(shown, hidden)
    print(f"arm share of the central frame: {share:.3f}; camera looking away: {arm_share(away, away_hidden):.3f}")
    assert share >= MIN_ARM_SHARE
    # the same check on a camera pointed away from the arm: it must fail
    assert arm_share(away, away_hidden) < MIN_ARM_SHARE
    assert arm_share(shown, shown) == 0.0


def test_replay_names_its_phases(replay):
    page = replay.read_text()
    assert 'id="safesysid-phases"' in page and "identification 0.0-1.0 s" in page


def test_first_ctrl_c_stops_the_simulation_the_second_aborts():
    import os
    import signal

    from safesysid.progress import RunDisplay, interruptible

    display = RunDisplay()
    with interruptible(display):
        os.kill(os.getpid(), signal.SIGINT)
        assert display.interrupted  # asked to stop, no exception: the run writes what it has
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)


def test_an_interrupted_run_stops_at_once_and_writes_what_was_done(tmp_path, capsys):
    """The monitor ends the simulation as soon as Ctrl-C was seen; summary.json and log.csv are
    still written, the summary says it did not succeed."""
    from safesysid.online import run_online
    from safesysid.progress import RunDisplay
    from safesysid.run_cli import _mark_interrupted
    from safesysid.scenario import SCENARIOS_DIR, load_scenario

    display = RunDisplay(progress=False, interrupted=True)
    scenario = load_scenario(SCENARIOS_DIR / "quickstart.yaml")
    summary = _mark_interrupted(tmp_path, run_online(scenario, tmp_path, live_meshcat=display))
    assert summary["success"] is False and summary["failure"] == "interrupted"
    assert summary["interrupted_at_s"] < 0.01  # the run was meant to last 7.5 s
    assert json.loads((tmp_path / "summary.json").read_text())["interrupted"] is True


def test_progress_line_names_phase_and_plan():
    from safesysid.progress import phase_at
    from safesysid.scenario import SCENARIOS_DIR, load_scenario

    s = load_scenario(SCENARIOS_DIR / "quickstart.yaml")  # 4 plans every 1.5 s, each 3 s long
    assert phase_at(0.2, s, None) == "identification, plan 1/4"
    assert phase_at(4.6, s, None) == "identification, plan 4/4"
    assert phase_at(7.6, s, 7.501) == "task"


def visibility_keys(page, path):
    """[(frame, visible)] of a path's '.visible' animation track in the page's recording: the
    msgpack bytes of the track (path, then clip, tracks, keys of time and boolean value)."""
    for blob in re.findall(r'fetch\("data:application/octet-binary;base64,([^"]+)"\)', page):
        data = base64.b64decode(blob)
        start = data.find(path.encode() + b"\xa4clip")
        if b"set_animation" not in data or start < 0:
            continue
        end = data.find(b"\xa4path", start)
        segment = data[start : end if end > 0 else None]
        keys = []
        for m in re.finditer(rb"\xa4time(\xcc.|\xcd..|[\x00-\x7f])\xa5value([\xc2\xc3])", segment, re.S):
            raw = m.group(1)
            keys.append((raw[0] if len(raw) == 1 else int.from_bytes(raw[1:], "big"), m.group(2) == b"\xc3"))
        return keys
    return []


def test_the_released_payload_leaves_the_gripper_in_the_replay(tmp_path):
    """After the release the welded payload is empty (no mass, no contact) but was still drawn in
    the gripper: the recording hides it from the release frame on, and the released copy is there."""
    from safesysid.online import run_online
    from safesysid.scenario import SCENARIOS_DIR, load_scenario

    summary = run_online(
        load_scenario(SCENARIOS_DIR / "experiment_a.yaml", overrides=["task: {settle_time_s: 0.2}"]),
        tmp_path,
        method="wrong",
    )
    release = [e["t"] for e in summary["events"] if e["kind"] == "release"]
    assert release, summary["events"]
    page = (tmp_path / "replay.html").read_text()
    held = "/drake/visualizer/payload/payload"
    assert held in meshcat_paths(page) and "/drake/visualizer/released_payload/released_payload" in meshcat_paths(page)
    fps = 64
    assert visibility_keys(page, held) == [(0, True), (round(release[0] * fps), False)]
