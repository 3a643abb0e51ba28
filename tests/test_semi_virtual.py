"""The semi-virtual path with the emulated sensor: real processes, real pty, real bus."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dammrl.devices.emulators.pad import Press, SensorEmulator
from dammrl.stack.recording import session_traces
from dammrl_core.task import TaskSettings
from schemas import DecisionRequest, EpisodeResult, Health, Intent, ModelChoice, SensorSample
from tests.busutil import Lines, Observer, free_port, start_patient, start_service, wait_for

pytestmark = pytest.mark.slow  # real processes on a real bus

FIRM_QUICK_EVERY_HALF_SECOND = [Press(0.1, 0.2, 1.0)]  # +1, E_big, repeated


def test_an_emulated_sensor_drives_a_semi_virtual_episode_to_the_goal(tmp_path: Path) -> None:
    """The hurried patient (quick presses: E_big) on the emulated pad, a fixed policy."""
    link, port = tmp_path / "ttySENSOR", free_port()
    observer = Observer(port)
    sensor = {"DAMMRL_INTENT_SOURCE": "pad", "DAMMRL_PAD_PORT": str(link)}
    fixed = {"DAMMRL_POLICY_KIND": "fixed", "DAMMRL_POLICY_HUMAN_MODEL": "1"}
    processes = [
        start_patient(link, port, human_model=1),
        start_service("sim", port),
        start_service("policy", port, **fixed),
        start_service("intent", port, **sensor),
        start_service("controller", port, DAMMRL_TASK_EPISODES="1", DAMMRL_TASK_SEED="8"),
    ]
    try:
        wait_for(lambda: bool(observer.of(EpisodeResult)), 120, "the episode to end")
    finally:
        for process in processes:
            process.terminate()
        for process in processes:
            process.wait(15)
        observer.close()
    result = observer.of(EpisodeResult)[0]
    assert isinstance(result, EpisodeResult) and result.success, result.reason
    intents = [i for i in observer.of(Intent) if isinstance(i, Intent)]
    assert intents and all(i.source == "pad" and i.person and i.human_model == 1 for i in intents)
    assert {i.u_h for i in intents} <= {-1, 1} and len(observer.of(SensorSample)) > 100


def test_the_intent_service_survives_an_unplugged_sensor_and_reconnects(tmp_path: Path) -> None:
    link, port = tmp_path / "ttySENSOR", free_port()
    observer = Observer(port)
    serial_env = {"DAMMRL_INTENT_SOURCE": "pad", "DAMMRL_PAD_PORT": str(link)}
    intent = start_service("intent", port, DAMMRL_PAD_RECONNECT_MAX_S="0.5", **serial_env)
    try:
        with SensorEmulator(link, FIRM_QUICK_EVERY_HALF_SECOND, loop_s=0.5):
            wait_for(lambda: len(observer.of(SensorSample)) > 20, 30, "samples")
        count = len(observer.of(SensorSample))
        reports = lambda: observer.of(Health)  # noqa: E731
        wait_for(
            lambda: any(isinstance(h, Health) and h.state == "degraded" for h in reports()),
            10,
            "the service to report the lost sensor",
        )
        assert intent.poll() is None
        with SensorEmulator(link, FIRM_QUICK_EVERY_HALF_SECOND, loop_s=0.5, seed=1):
            wait_for(lambda: len(observer.of(SensorSample)) > count + 20, 30, "samples again")
        assert intent.poll() is None
    finally:
        intent.terminate()
        intent.wait(15)
        observer.close()
    time.sleep(0.1)


def test_a_simulated_patient_at_the_pad_is_recognised_by_the_policys_posterior(
    tmp_path: Path,
) -> None:
    """The careful patient (held presses, 90 % correct, slow) through the whole semi-virtual
    path: pty frames, decoder, intent service, learned policy estimating the human; the
    session is recorded and drawn as the paper's S2 figure."""
    link, port, mcap = tmp_path / "ttySENSOR", free_port(), tmp_path / "s2.mcap"
    observer = Observer(port)
    recorder = start_service("recorder", port, DAMMRL_RECORDER_OUT=str(mcap))
    wait_for(lambda: any(getattr(h, "service", "") == "recorder" for h in observer.of(Health)),
             30, "the recorder")  # fmt: skip
    processes = [
        start_patient(link, port, human_model=2),
        start_service("sim", port),
        start_service("policy", port),
        start_service("intent", port, DAMMRL_INTENT_SOURCE="pad", DAMMRL_PAD_PORT=str(link)),
        start_service("controller", port, DAMMRL_TASK_EPISODES="1", DAMMRL_TASK_SEED="3"),
    ]
    try:
        wait_for(lambda: bool(observer.of(EpisodeResult)), 150, "the episode to end")
    finally:
        for process in [*processes, recorder]:
            process.terminate()
        for process in [*processes, recorder]:
            process.wait(15)
        observer.close()
    intents = [i for i in observer.of(Intent) if isinstance(i, Intent)]
    assert len(intents) >= 6 and all(i.source == "pad" and i.person for i in intents)
    assert all(i.human_model == 2 for i in intents), "held presses decode as E_small"
    answers = [c for c in observer.of(ModelChoice) if isinstance(c, ModelChoice) and c.request > 6]
    assert answers and all(c.posterior is not None for c in answers)
    careful = [c.posterior[1] > 0.5 for c in answers if c.posterior is not None]
    assert sum(careful) >= 0.9 * len(careful), "the posterior finds the careful sub-model"
    result = observer.of(EpisodeResult)[0]
    assert isinstance(result, EpisodeResult) and result.success, result.reason

    png = tmp_path / "s2.png"
    plotted = subprocess.run(
        [sys.executable, "-m", "dammrl", "recording", "plot", str(mcap), "-o", str(png)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert plotted.returncode == 0, plotted.stderr
    traces = session_traces(mcap)
    assert traces.pressure_normalised and traces.pressure.max() > 0.8  # firm presses seen
    assert len(traces.decisions) == len(intents) and len(traces.error_t) > 100
    final_error = float(np.linalg.norm(traces.error_m[-1]))
    assert final_error < TaskSettings().goal_tolerance_m and png.stat().st_size > 20_000


def test_the_intent_service_survives_every_wire_fault_and_still_answers(tmp_path: Path) -> None:
    link, port = tmp_path / "ttySENSOR", free_port()
    observer = Observer(port)
    serial_env = {"DAMMRL_INTENT_SOURCE": "pad", "DAMMRL_PAD_PORT": str(link)}
    intent = start_service("intent", port, **serial_env)
    faults = [
        bytes(range(256)) * 4,  # binary garbage
        b"$P,12,3456" * 10 + b"\r\n",  # an overlong line
        b"$P,12,",  # a cut frame (the next frame starts before it ends)
        b"$P,1,99999*00\r\n",  # out of range and a wrong checksum
    ]
    try:
        with SensorEmulator(link, []) as pad:
            wait_for(lambda: len(observer.of(SensorSample)) > 20, 30, "samples")
            for fault in faults:
                pad.inject(fault)
            pad.corrupt_next = 5
            pad.silent.set()  # the sensor stops sending
            wait_for(lambda: _health_says(observer, "silent"), 10, "a silent-sensor report")
            pad.silent.clear()
            count = len(observer.of(SensorSample))
            wait_for(lambda: len(observer.of(SensorSample)) > count + 20, 10, "samples again")
            assert intent.poll() is None
            observer.session.put("dammrl/intent/request", _request())
            pad.press(1.0, 0.2)
            wait_for(lambda: bool(observer.of(Intent)), 10, "the press to answer the request")
            wait_for(lambda: _health_says(observer, "frames, "), 5, "a health report")
    finally:
        intent.terminate()
        intent.wait(15)
        observer.close()
    reports = [h for h in observer.of(Health) if isinstance(h, Health) and h.service == "intent"]
    bad = int(reports[-1].detail.split(" frames, ")[1].split()[0])
    assert bad >= 8, reports[-1].detail  # garbage, overlong, cut, range/checksum, 5 corrupted


def _health_says(observer: Observer, text: str) -> bool:
    return any(isinstance(h, Health) and text in h.detail for h in observer.of(Health))


def _request() -> bytes:
    from schemas import Header, encode

    return encode(
        DecisionRequest(
            header=Header(stamp_ns=time.time_ns(), seq=0, source="controller"),
            episode=1, seed=1, request=0, t_s=0.0, ee_pos_m=(0.0, 0.0, 0.0), goal_m=(0.3, 0.0, 0.0),
            primary_axis=0, human_model=1,
        )
    )  # fmt: skip


def test_a_patient_started_before_the_stack_says_so_and_joins_it(tmp_path: Path) -> None:
    """The README's order (the emulated pad first, then `dammrl up` on its port, TLS by
    default): the patient says within seconds that nothing answers, then finds the run's
    credentials from the port and answers its requests."""
    link, port = tmp_path / "ttyPAD", free_port()
    patient = subprocess.Popen(
        [sys.executable, "-m", "dammrl", "sensor", "emulate", "--pattern", "patient", "--link",
         str(link), "--connect", f"tcp/127.0.0.1:{port}"],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert patient.stderr is not None
        said = Lines(patient.stderr)
        said.wait_for("nothing answers at", 10)
        up = subprocess.run(
            [sys.executable, "-m", "dammrl", "up", "--mode", "semi-virtual", "--port", str(link),
             "--episodes", "1", "--json", "--bus-port", str(port), "--model", "1,1"],
            capture_output=True, text=True, timeout=240,
        )  # fmt: skip
        assert up.returncode == 0, up.stderr[-2000:]
        assert '"success": true' in up.stdout, up.stdout + up.stderr[-2000:]
        said.wait_for("joined the stack at tls/127.0.0.1:", 10)
    finally:
        patient.terminate()
        patient.wait(10)
