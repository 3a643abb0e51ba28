"""What keeps a person's decisions true whatever their sensor's sender does, without LSL:
decisions belong to the request they began in, streams are checked against the
calibration, timestamps stay true (jumps corrected, gaps counted into the recording),
and the intent service lives through a failing source and holds its problems in Health
long enough to be seen."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dammrl_core.intent.emg.calibration import StreamDescription
from dammrl_core.intent.lsl import mismatch
from dammrl_core.intent.source import Chunk, Decided, belongs_to_request
from dammrl_core.intent.stamps import StreamClock
from dammrl_core.models import ModelSet
from schemas import Header, SessionControl, SignalChunk, encode, key
from services.intent.config import IntentSettings
from services.intent.node import PROBLEM_HOLD_S, IntentNode, RawBacklog, RecentProblems
from services.recorder.core import McapRecorder
from tests.test_nodes import FakeBus, ScriptedPerson, _request

RATE = 1000.0


# ---- whose decision ------------------------------------------------------------------------------
def test_a_decision_belongs_to_the_request_it_began_in() -> None:
    assert belongs_to_request(10.0, None, 0.1) == "no request open"
    assert belongs_to_request(10.0, 10.5, 0.1) == "began 0.50 s before the request opened"
    assert belongs_to_request(10.45, 10.5, 0.1) == ""  # within the onset estimate's error
    assert belongs_to_request(11.0, 10.5, 0.1) == ""


# ---- the stream against the calibration ----------------------------------------------------------
CALIBRATED = StreamDescription(name="ForearmEMG", type="EMG", channel_count=4,
                               nominal_srate_hz=2000.0, channel_labels=["F1", "F2", "E1", "E2"],
                               units=["microvolts"] * 4)  # fmt: skip


@pytest.mark.parametrize(("change", "words"), [
    ({"nominal_srate_hz": 1000.0}, "runs at 1000 Hz, the calibration at 2000 Hz"),
    ({"channel_count": 3, "channel_labels": [], "units": []}, "has 3 channels, the calibration 4"),
    ({"type": "EEG"}, "of type 'EEG', the calibration's 'EMG'"),
    ({"channel_labels": ["F1", "E1", "F2", "E2"]}, "channel 1 label is 'E1', the calibration's"),
    ({"units": ["millivolts"] * 4}, "channel 0 unit is 'millivolts', the calibration's"),
    ({"channel_labels": [], "units": []}, "channel 0 label is 'none'"),
])  # fmt: skip
def test_a_stream_unlike_the_calibration_is_refused_in_one_line(
    change: dict[str, Any], words: str
) -> None:
    found = CALIBRATED.model_copy(update=change)
    assert words in str(mismatch(found, CALIBRATED, rate_tolerance=0.005))


def test_a_stream_no_calibration_can_describe_is_refused_in_one_line() -> None:
    from dammrl_core.intent.lsl import LslSource

    class Irregular:  # an LSL marker stream of the same name: no regular rate
        def name(self) -> str:
            return "ForearmEMG"

        def type(self) -> str:
            return "EMG"

        def channel_count(self) -> int:
            return 4

        def nominal_srate(self) -> float:
            return 0.0

        def source_id(self) -> str:
            return ""

        def hostname(self) -> str:
            return "amp"

        def desc(self) -> Any:
            raise AssertionError("not reached: no labels asked of an unusable stream")

    source = LslSource.__new__(LslSource)
    source.settings = type("S", (), {"stream": "ForearmEMG", "rate_tolerance": 0.005})()  # type: ignore[assignment]
    source.calibration = type("C", (), {"stream": CALIBRATED})()  # type: ignore[assignment]
    line = str(source._unfit(Irregular()))
    assert "stream 'ForearmEMG' cannot be used: nominal_srate_hz" in line, line


def test_a_stream_within_the_rate_tolerance_and_unlabelled_calibrations_pass() -> None:
    assert mismatch(CALIBRATED.model_copy(update={"nominal_srate_hz": 2008.0}), CALIBRATED,
                    rate_tolerance=0.005) is None  # fmt: skip
    unlabelled = CALIBRATED.model_copy(update={"channel_labels": [], "units": []})
    assert mismatch(CALIBRATED, unlabelled, rate_tolerance=0.0) is None


# ---- the stream's clock --------------------------------------------------------------------------
def _feed(clock: StreamClock, chunks: int, start_s: float, stamp_offset_s: float = 0.0,
          late_s: float = 0.003) -> list[tuple[np.ndarray, float]]:  # fmt: skip
    """``chunks`` of 20 samples from ``start_s`` (arrival clock), stamped with an offset."""
    out = []
    for k in range(chunks):
        t = start_s + k * 0.02 + np.arange(20) / RATE
        timed = clock.take(t + stamp_offset_s, float(t[-1]) + late_s)
        out.append((timed.times_s, float(t[-1])))
    return out


def test_a_jump_of_the_senders_clock_is_corrected_to_this_machines() -> None:
    """After a +5 s jump the recorded onsets stayed 5 s ahead."""
    clock = StreamClock(RATE, max_gap_s=0.25, jitter_s=0.05)
    _feed(clock, 50, 100.0)
    after = _feed(clock, 50, 101.0, stamp_offset_s=5.0)
    assert clock.jumps == 1 and clock.offset_s == pytest.approx(-5.0, abs=0.01)
    for times, acquired in after:
        assert times[-1] == pytest.approx(acquired, abs=0.01)
    back = _feed(clock, 50, 102.0, stamp_offset_s=5.0 - 1.0)  # then a second back
    assert clock.jumps == 2 and back[-1][0][-1] == pytest.approx(back[-1][1], abs=0.01)
    assert clock.missing == 0


def test_stamps_of_a_clock_of_the_senders_own_are_anchored_to_ours_at_once() -> None:
    clock = StreamClock(RATE, max_gap_s=0.25, jitter_s=0.05)
    times, acquired = _feed(clock, 1, 500.0, stamp_offset_s=1.7e9)[0]  # Unix time stamps
    assert times[-1] == pytest.approx(acquired, abs=0.01) and clock.jumps == 1


def test_a_gap_is_counted_and_a_busy_senders_jitter_is_not() -> None:
    """A recorded raw stream lost 93 ms across a 2 s freeze without being counted."""
    clock = StreamClock(RATE, max_gap_s=0.25, jitter_s=0.05)
    rng = np.random.default_rng(0)
    _feed(clock, 50, 100.0)
    for k in range(100):  # each chunk pushed up to 30 ms late, stamped back from then
        t = 101.0 + k * 0.02 + rng.uniform(0.0, 0.03) + np.arange(20) / RATE
        clock.take(t, float(t[-1]) + 0.003)
    clock.take(103.04 + np.arange(20) / RATE, 103.062)  # on time: the last at 103.059
    assert (clock.gaps, clock.missing, clock.jumps) == (0, 0, 0)
    timed = clock.take(103.153 + np.arange(20) / RATE, 103.2)  # 93 samples lost between
    assert (timed.missing, clock.gaps, clock.jumps) == (93, 1, 0)


def test_a_sender_delivering_half_its_announced_rate_is_seen() -> None:
    clock = StreamClock(RATE, max_gap_s=0.25, jitter_s=0.05)
    for k in range(300):  # 10 samples every 20 ms, stamped 2 ms apart: 500 a second
        t = 100.0 + k * 0.02 + np.arange(10) / 500.0
        clock.take(t, float(t[-1]) + 0.003)
    assert clock.delivered_hz() == pytest.approx(500.0, rel=0.01)


# ---- raw samples into the recording --------------------------------------------------------------
def test_samples_dropped_before_the_bus_count_as_missing_in_the_next_message() -> None:
    backlog = RawBacklog()
    times = np.arange(12_000) / RATE  # 12 s waiting: more than the backlog holds (5 s)
    for k in range(0, 12_000, 1000):
        backlog.add(Chunk("emg", RATE, np.zeros((1000, 8)), times[k : k + 1000], missing=3))
    sent = []
    while (chunk := backlog.take(len(sent) * 0.021)) is not None:
        sent.append(chunk)
    assert backlog.dropped == 7000
    missing = [c.missing for c in sent]
    assert missing[0] == 7000 + 8 * 3 and sum(missing) == 7000 + 12 * 3
    assert sum(len(c.times_s) for c in sent) == 5000


def _chunk(seq: int, missing: int, corrected: float) -> bytes:
    header = Header(stamp_ns=seq + 1, seq=seq, source="intent")
    return encode(SignalChunk(header=header, stream="emg", rate_hz=RATE, stamps_ns=[seq + 1],
                              samples=[[0.0, 1.0]], missing=missing,
                              clock_corrected_s=corrected))  # fmt: skip


def test_the_recording_counts_a_raw_streams_missing_samples_and_clock_jumps(
    tmp_path: Path,
) -> None:
    from dammrl.stack.recording import info

    recorder = McapRecorder(tmp_path / "r.mcap", "dammrl", {}, 1 << 20)
    topic = key("dammrl", SignalChunk)
    for seq, missing, corrected in ((0, 0, 0.0), (1, 93, 0.0), (2, 0, -5.0), (3, 0, -5.0)):
        recorder.record(topic, _chunk(seq, missing, corrected), seq + 1)
    recorder.finish()
    recorded = info(tmp_path / "r.mcap")
    loss = json.loads(recorded["metadata"]["dammrl.loss"]["raw_streams"])
    assert loss["emg"] == {"chunks": 4, "samples": 4, "missing_samples": 93, "gaps": 1,
                           "clock_jumps": 1, "clock_corrected_s": -5.0}  # fmt: skip
    assert recorded["raw_streams"] == loss  # a cut file's are counted from its messages too
    shown = subprocess.run([sys.executable, "-m", "dammrl", "recording", "info",
                            str(tmp_path / "r.mcap")], capture_output=True, text=True,
                           check=True).stdout  # fmt: skip
    assert "raw stream 'emg': 4 samples, 93 missing in 1 gaps, 1 clock jumps corrected" in shown


# ---- the service lives, its problems are seen ----------------------------------------------------
class HealthBus(FakeBus):
    def __init__(self) -> None:
        super().__init__()
        self.health: list[tuple[str, str]] = []

    def report_health(self, state: str = "ok", detail: str = "", force: bool = False) -> None:
        self.health.append((state, detail))


class FailingPerson(ScriptedPerson):
    """A plug-in source whose device raises (until ``mended``), and that re-baselines."""

    def __init__(self) -> None:
        super().__init__()
        self.failing, self.rebaselined = True, 0

    def poll(self, now_s: float) -> Decided | None:
        if self.failing:
            raise OSError("device unplugged")
        return super().poll(now_s)

    def rebaseline(self) -> str:
        self.rebaselined += 1
        return "measuring"


def test_a_source_that_raises_is_stated_and_the_service_goes_on() -> None:
    """A sender without a source id, lost: pylsl raised in the source's poll and the
    intent service exited (the whole stack stopped)."""
    bus, person = HealthBus(), FailingPerson()
    node = IntentNode(IntentSettings(), person, "lsl", ModelSet(), bus)  # type: ignore[arg-type]
    node._dispatch(_request(1))
    node.step()
    node.step()
    assert bus.health[-1][0] == "degraded" and "device unplugged" in bus.health[-1][1]
    assert bus.published == []  # nothing answered: the arm holds at its request
    person.failing = False
    person.coming.append(Decided(u_h=1, human_model=2, confidence=0.9, decision_s=0.5))
    node.retry_at.clear()  # its retry due (SOURCE_RETRY_S later)
    node.step()
    state, detail = bus.health[-1]
    assert state == "ok" and "recently: the source failed reading" in detail
    assert [m.request for m in bus.published] == [1]


def test_the_therapists_rebaseline_reaches_the_source() -> None:
    bus, person = HealthBus(), FailingPerson()
    node = IntentNode(IntentSettings(), person, "lsl", ModelSet(), bus)  # type: ignore[arg-type]
    node._dispatch(SessionControl(header=Header(stamp_ns=1, seq=0, source="operator"), episode=1,
                                  action="rebaseline", who="T01"))  # fmt: skip
    assert person.rebaselined == 1


def test_a_problem_of_a_tenth_of_a_second_stays_in_health_long_enough_to_be_seen() -> None:
    """Fault lines lasted ~0.1 s in Health: `dammrl status` (2.5 s) rarely showed them."""
    problems = RecentProblems()
    problems.see("channel 3 flat (an electrode off?)", 100.0)
    problems.see(None, 100.1)
    assert "channel 3 flat" in str(problems.recent(100.1 + PROBLEM_HOLD_S - 0.5))
    assert "for 0.1 s" in str(problems.recent(103.0))
    assert problems.recent(100.1 + PROBLEM_HOLD_S + 0.5) is None
    problems.see("stream 'x' silent for 0.6 s (lost?)", 200.0)
    problems.see("stream 'x' silent for 3.1 s (lost?)", 202.5)  # one problem as it grows
    problems.see(None, 203.0)
    assert "silent for 3.1 s (lost?) (for 3.0 s" in str(problems.recent(204.0))


# ---- the participant is told --------------------------------------------------------------------
# what the participant's page says of a question answered, closed or not counted:
# tests/test_display_screens.py (the page's screens)


def test_a_request_opens_when_its_controller_stamped_it_not_when_it_arrived() -> None:
    """Under load a request reached the intent service 0.3 s after the participant saw it:
    their prompt contraction then 'began before the request opened' and counted for
    nothing. Clocks that disagree by more than MAX_TRANSIT_S are not believed."""
    from services.intent.node import MAX_TRANSIT_S, opened_s

    now_wall, now = time.time_ns(), time.monotonic()
    assert opened_s(now_wall - 300_000_000) == pytest.approx(now - 0.3, abs=0.05)
    assert opened_s(now_wall + 5_000_000_000) == pytest.approx(now, abs=0.05)  # ahead
    assert opened_s(now_wall - 60_000_000_000) == pytest.approx(now - MAX_TRANSIT_S, abs=0.05)
    bus, person = HealthBus(), ScriptedPerson()
    opened: list[float] = []
    person.ask = lambda ask, now_s: opened.append(now_s)  # type: ignore[method-assign]
    node = IntentNode(IntentSettings(), person, "pad", ModelSet(), bus)  # type: ignore[arg-type]
    late = _request(1).model_copy(update={"header": Header(
        stamp_ns=time.time_ns() - 400_000_000, seq=0, source="controller")})  # fmt: skip
    node._dispatch(late)
    assert opened == [pytest.approx(time.monotonic() - 0.4, abs=0.05)]


def test_a_decision_made_just_before_its_request_arrived_answers_it(tmp_path: Path) -> None:
    """Under load the request reached the service after the person's quick contraction
    had ended: 'no request open', the request stayed open and the person had to answer
    again (8 of 30 in the latency benchmark at load 30)."""
    from dammrl_core.intent.emg.calibration import save_calibration
    from dammrl_core.intent.emg.decoder import Contraction
    from dammrl_core.intent.emg.training import train
    from dammrl_core.intent.lsl import CLAIM_WITHIN_S, LslSettings, LslSource
    from dammrl_core.intent.source import Ask
    from tests.test_wearable import STREAM, cued_session

    path = save_calibration(train(*cued_session(), STREAM), tmp_path / "p.json")
    source = LslSource(LslSettings(stream="emg", calibration_file=path))
    now = time.monotonic()

    def contraction(onset_s: float) -> Contraction:
        return Contraction(1, 1, 0.99, onset_s, onset_s + 0.3, onset_s + 0.4, 6, (0.0,),
                           True, "")  # fmt: skip

    def ask(opened_s: float, number: int) -> None:
        source.ask(Ask(1, number, 0, 0.0, np.zeros(3), np.ones(3), 0, 1), opened_s)

    assert source._take_decision(contraction(now - 0.5)) is None  # no request here yet
    ask(now - 0.7, 1)  # stamped before the contraction began: it is its answer
    decided = source.poll(time.monotonic())
    assert decided is not None and decided.decision_s == pytest.approx(0.2)
    assert [(e.request, e.acted) for e in source.evidence()] == [(1, True)]
    source._take_decision(contraction(now - 0.5))
    ask(now - 0.2, 2)  # stamped after it began: meant for another moment
    assert source.poll(time.monotonic()) is None
    assert [(e.acted, e.reason) for e in source.evidence()] == [
        (False, "began 0.30 s before the request opened")]  # fmt: skip
    source.cancel()
    source._take_decision(contraction(time.monotonic()))
    source.unclaimed = (source.unclaimed[0], time.monotonic() - CLAIM_WITHIN_S - 0.1)  # type: ignore[index]
    assert source.poll(time.monotonic()) is None  # no request came in time: evidence only
    assert [(e.acted, e.reason) for e in source.evidence()] == [(False, "no request open")]


def test_a_stream_wider_than_the_bus_carries_is_refused_at_its_description() -> None:
    """A 128-channel HD-EMG stream calibrated and attached, then its first raw chunk failed
    the bus's schema (64 channels at most) and ended the intent service, and the run."""
    from dammrl_core.intent.emg.calibration import MAX_STREAM_CHANNELS
    from schemas.messages import MAX_CHANNELS

    assert MAX_STREAM_CHANNELS == MAX_CHANNELS
    StreamDescription(name="HD", channel_count=MAX_CHANNELS, nominal_srate_hz=2048)
    with pytest.raises(ValueError, match="less than or equal to 64"):
        StreamDescription(name="HD", channel_count=128, nominal_srate_hz=2048)
