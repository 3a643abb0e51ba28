"""A session through the real stack: ``kill -9`` of the runner, then of a service,
mid-block; each time ``dammrl session run`` again resumes, and in the end every trial is
done exactly once and every recording still holds the results its trials point at."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dammrl.stack.options import check_port
from dammrl.stack.recording import read_recording
from dammrl_core.errors import DammrlError
from schemas import EpisodeResult
from tests.busutil import free_port

pytestmark = pytest.mark.slow

PROTOCOL = """\
format: 1
name: crash-test
version: "1"
blocks:
  - {name: event, trials: 5, seed: 7100100, condition: {policy: fixed, model: [2, 1]}}
  - {name: fixed, trials: 5, seed: 7100100,
     condition: {trigger: fixed, policy: fixed, model: [2, 1]}}
"""


def _start(tmp_path: Path, port: int) -> subprocess.Popen[bytes]:
    log = open(tmp_path / "runner.log", "ab")  # noqa: SIM115  (the child writes it)
    return subprocess.Popen(
        [sys.executable, "-m", "dammrl", "session", "run", "--participant", "P001",
         "--protocol", str(tmp_path / "protocol.yaml"), "--root", str(tmp_path / "sessions"),
         "--lockstep", "--bus-port", str(port), "--operator", "T1", "--no-display"],
        stdin=subprocess.DEVNULL, stdout=log, stderr=log,
    )  # fmt: skip


def _done(tmp_path: Path) -> list[dict[str, object]]:
    path = tmp_path / "sessions" / "P001" / "ses-01" / "trials.jsonl"
    lines = path.read_text().splitlines() if path.exists() else []
    return [json.loads(line) for line in lines]


def _wait(condition: object, timeout_s: float, what: str, tmp_path: Path) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if callable(condition) and condition():
            return
        time.sleep(0.1)
    log = (tmp_path / "runner.log").read_text(errors="replace")[-3000:]
    raise AssertionError(f"no {what} in {timeout_s} s; the runner said:\n{log}")


def _port_free(port: int) -> bool:
    try:
        check_port(port)
    except DammrlError:
        return False
    return True


def _child(parent: int, service: str) -> int:
    """The pid of ``services.<service>`` started by ``parent``."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ")
        except (OSError, IndexError, ValueError):
            continue
        if ppid == parent and f"services.{service}".encode() in command:
            return int(entry.name)
    raise AssertionError(f"no {service} under {parent}")


def _kill_after(tmp_path: Path, port: int, trials: int, victim: str | None) -> None:
    """Run the session until ``trials`` trials are logged, then kill -9 the runner (None)
    or one of its services; wait until everything it started is gone."""
    trials = max(trials, len(_done(tmp_path)) + 1)  # at least one trial in this run
    runner = _start(tmp_path, port)
    try:
        _wait(lambda: len(_done(tmp_path)) >= trials, 180, f"{trials} trials", tmp_path)
        pid = runner.pid if victim is None else _child(runner.pid, victim)
        os.kill(pid, signal.SIGKILL)
        runner.wait(60)  # a dead service ends the runner's run with an error
    finally:
        if runner.poll() is None:
            runner.kill()
            runner.wait()
    _wait(lambda: _port_free(port), 30, "free port (the services die with the runner)", tmp_path)


def test_a_session_killed_again_and_again_resumes_and_runs_every_trial_exactly_once(
    tmp_path: Path,
) -> None:
    """2 blocks x 5 trials: kill -9 of the runner, then of each service of the stack, at
    successive trials; each time `dammrl session run` again resumes. A killed recorder is
    restarted by the stack itself (the session goes on)."""
    (tmp_path / "protocol.yaml").write_text(PROTOCOL)
    port = free_port()
    # mid-block (a block's last trial ends its stack: a kill then would hit a stopping one)
    for after, victim in ((1, None), (2, "controller"), (3, "sim"), (6, "intent"), (7, "policy")):
        _kill_after(tmp_path, port, after, victim)
    runner = _start(tmp_path, port)
    at_least = max(8, len(_done(tmp_path)) + 1)
    assert at_least < 10, "the session ran past the recorder's kill point"
    _wait(lambda: len(_done(tmp_path)) >= at_least, 180, "trials", tmp_path)
    os.kill(_child(runner.pid, "recorder"), signal.SIGKILL)
    assert runner.wait(300) == 0, (tmp_path / "runner.log").read_text()[-3000:]

    done = _done(tmp_path)
    assert sorted(int(str(t["trial"])) for t in done) == list(range(1, 11)), done
    folder = tmp_path / "sessions" / "P001" / "ses-01"
    events = [json.loads(line) for line in (folder / "events.jsonl").read_text().splitlines()]
    whats = [e["what"] for e in events]
    assert whats.count("resume") == 5 and whats[-1] == "end" and whats.count("stopped") == 4
    assert all(e["who"] == "T1" for e in events)
    assert "restarted into a new file" in (tmp_path / "runner.log").read_text()
    for trial in done:  # its recording holds its result, whatever killed the run after it
        recording = read_recording(folder / str(trial["recording"]))
        results = [m for _, m in recording.decoded(EpisodeResult)]
        assert any(r.episode == trial["episode"] and r.seed == trial["seed"] for r in results)
        study = json.loads(recording.metadata["dammrl.session"]["study"])
        assert study["participant"] == "P001" and trial["trial"] in study["trials"]


def test_a_pause_holds_the_arm_without_a_jump_and_an_again_ends_the_reach() -> None:
    """On the real stack: pause a reach under way for 2 s, resume it, then run the next
    one again (it ends as a skip or an end of block does: ``ENDS_REACH``). The reference
    never steps further than in ordinary running; the paused reach still succeeds and
    its time leaves the pause out."""
    import threading

    from dammrl.stack.launch import Stack
    from dammrl.stack.options import StackOptions
    from schemas import Header, JointCommand, SessionControl, decode, encode, key

    commands: list[tuple[float, JointCommand]] = []
    results: list[EpisodeResult] = []
    keep: list[object] = []
    marks: dict[str, float] = {}

    def control(hub: object, episode: int, action: str) -> None:
        header = Header(stamp_ns=time.time_ns(), seq=len(marks), source="operator")
        message = SessionControl(header=header, episode=episode, action=action, who="T1",
                                 why="a test")  # fmt: skip
        marks[f"{action}{episode}"] = time.monotonic()
        hub.put(key("dammrl", SessionControl), encode(message))  # type: ignore[attr-defined]

    def script(hub: object) -> None:
        deadline = time.monotonic() + 60
        while len(commands) < 300 and time.monotonic() < deadline:  # a reach under way
            time.sleep(0.05)
        control(hub, 1, "pause")
        time.sleep(2.0)
        control(hub, 1, "resume")
        while not results and time.monotonic() < deadline + 60:
            time.sleep(0.05)
        time.sleep(1.0)
        control(hub, 2, "again")

    def on_up(hub: object) -> None:
        def take(sample: object) -> None:
            payload = sample.payload.to_bytes()  # type: ignore[attr-defined]
            commands.append((time.monotonic(), decode(JointCommand, payload)))

        keep.append(hub.declare_subscriber(key("dammrl", JointCommand), take))  # type: ignore[attr-defined]
        threading.Thread(target=script, args=(hub,), daemon=True).start()

    options = StackOptions(episodes=2, seed=7100100, model=(2, 1), port=free_port())
    stack = Stack(options, out=lambda line: None, info=lambda line: None,
                  on_result=results.append, on_up=on_up)  # fmt: skip
    assert stack.run() == 0
    first, second = results
    assert first.success, first.reason
    assert second.outcome == "skipped" and "skipped by T1: a test" in second.reason
    paused = [c for t, c in commands if marks["pause1"] + 0.3 < t < marks["resume1"]]
    assert paused and all(c.dq_ref_rad_s == (0.0,) * 6 for c in paused)  # held at rest
    assert len({c.q_ref_rad for c in paused}) == 1  # at one posture
    # No jump at the resume: its first step moves the reference no faster than any other
    # step of the reach. Speeds per second of the states answered, not per command: under
    # load a late tick answers a later state, and its step is larger by as much.
    episode1 = [(t, c) for t, c in commands if c.episode == 1]
    steps = np.abs(np.diff(np.array([c.q_ref_rad for _, c in episode1]), axis=0)).max(axis=1)
    answered_s = np.diff(np.array([c.state_stamp_ns for _, c in episode1])) / 1e9
    speeds = steps / np.maximum(answered_s, 1e-4)
    resumed = next(i for i, (t, _) in enumerate(episode1[:-1])
                   if t > marks["resume1"] and steps[i] > 0)  # fmt: skip
    ordinary = np.delete(speeds, resumed)
    assert speeds[resumed] <= ordinary.max(), (steps[resumed], answered_s[resumed], ordinary.max())
    reach_s = first.t_total_s
    took_s = max(t for t, c in commands if c.episode == 1) - min(
        t for t, c in commands if c.episode == 1
    )
    assert took_s - reach_s > 1.5, (took_s, reach_s)  # the pause is not the reach's time


def test_the_therapist_takes_the_decisions_over_and_hands_them_back() -> None:
    """On the real stack: taken over, the therapist's decisions answer the requests (the
    simulated human's are dropped); after three, handed back, the human answers again,
    and the reach reaches the button."""
    import threading

    from dammrl.stack.launch import Stack
    from dammrl.stack.options import StackOptions
    from schemas import DecisionRequest, Header, Intent, SessionControl, decode, encode, key

    intents: list[Intent] = []
    results: list[EpisodeResult] = []
    keep: list[object] = []
    answered: set[int] = set()  # requests the therapist's decision answered
    sent = [0]

    def control(hub: object, action: str, **decision: int) -> None:
        header = Header(stamp_ns=time.time_ns(), seq=sent[0], source="operator")
        sent[0] += 1
        message = SessionControl(header=header, episode=1, action=action, who="T1",
                                 **decision)  # type: ignore[arg-type]  # fmt: skip
        hub.put(key("dammrl", SessionControl), encode(message))  # type: ignore[attr-defined]

    def on_up(hub: object) -> None:
        control(hub, "take")

        def request(sample: object) -> None:  # asked, or asked again: the therapist decides
            asked = decode(DecisionRequest, sample.payload.to_bytes())  # type: ignore[attr-defined]
            if len(answered) < 3 and asked.request not in answered:
                axis = asked.primary_axis
                ahead = asked.goal_m[axis] - asked.ee_pos_m[axis]
                control(hub, "decide", u_h=1 if ahead > 0 else -1, human_model=1)

        def intent(sample: object) -> None:
            answer = decode(Intent, sample.payload.to_bytes())  # type: ignore[attr-defined]
            intents.append(answer)
            if answer.source == "operator" and answer.request not in answered:
                answered.add(answer.request)
                if len(answered) == 3:
                    threading.Timer(0.5, control, args=(hub, "give")).start()

        subscribe = hub.declare_subscriber  # type: ignore[attr-defined]
        keep.extend([subscribe(key("dammrl", DecisionRequest), request),
                     subscribe(key("dammrl", Intent), intent)])  # fmt: skip

    options = StackOptions(episodes=1, seed=7100100, model=(1, 1), port=free_port())
    stack = Stack(options, out=lambda line: None, info=lambda line: None,
                  on_result=results.append, on_up=on_up)  # fmt: skip
    assert stack.run() == 0
    assert results[0].success, results[0].reason
    sources = [i.source for i in intents]
    operator = {i.request for i in intents if i.source == "operator"}
    assert operator and operator <= answered, sources
    assert "simulated" in sources[sources.index("operator") :], sources  # handed back
