"""The messages of the bus: frozen pydantic models, SI units in field names.

Every message carries a :class:`Header`. Unknown fields, NaN and infinities are rejected,
arrays have fixed lengths (6 joints, 3 task axes). Ranges that depend on the robot (joint
limits, effort limits) are checked by the receiving node against its robot description.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

Finite = Annotated[float, Field(allow_inf_nan=False)]
Vec3 = tuple[Finite, Finite, Finite]  # task-frame vector (x, y, z)
Joints = tuple[Finite, Finite, Finite, Finite, Finite, Finite]  # one value per joint, base first
NonNegativeJoints = tuple[
    Annotated[float, Field(ge=0, allow_inf_nan=False)],
    Annotated[float, Field(ge=0, allow_inf_nan=False)],
    Annotated[float, Field(ge=0, allow_inf_nan=False)],
    Annotated[float, Field(ge=0, allow_inf_nan=False)],
    Annotated[float, Field(ge=0, allow_inf_nan=False)],
    Annotated[float, Field(ge=0, allow_inf_nan=False)],
]
HumanModel = Annotated[int, Field(ge=1, le=2)]  # i: 1 = E_big, 2 = E_small
RobotModel = Annotated[int, Field(ge=1, le=8)]  # j: step vector (see the model set)
Trigger = Literal["event", "fixed"]


class Header(BaseModel):
    """Who published, when (publisher clock), and the publisher's sequence number."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    stamp_ns: int = Field(ge=0, description="publisher wall clock, ns since the Unix epoch")
    seq: int = Field(ge=0, description="per-publisher sequence number, +1 per message")
    source: str = Field(min_length=1, max_length=64, description="publishing service id")


class Message(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    header: Header


class RobotState(Message):
    """The arm at one instant (sim or robot)."""

    episode: int = Field(ge=0, description="episode the state belongs to (0 before the first)")
    t_s: Finite = Field(ge=0, description="robot / simulation clock [s]")
    q_rad: Joints
    dq_rad_s: Joints
    tau_nm: Joints = Field(description="torques actually applied, after saturation [N m]")
    ee_pos_m: Vec3
    ee_vel_m_s: Vec3
    button_pressed: bool
    button_travel_m: Finite
    holding: bool = Field(description="commands are stale: the arm holds its position")
    q_ref_applied_rad: Joints | None = Field(
        None, description="joint reference the arm applies (after its own caps)"
    )
    command_answers_ns: int | None = Field(
        None,
        ge=0,
        description="header stamp of the state the command in force answered "
        "(none: a hold, or no command yet); a late command shows as an older stamp",
    )


class JointCommand(Message):
    """Joint impedance command: tau = tau_ff + kp (q_ref - q) + kd (dq_ref - dq)."""

    episode: int = Field(ge=0)
    state_stamp_ns: int = Field(ge=0, description="header stamp of the RobotState answered")
    q_ref_rad: Joints
    dq_ref_rad_s: Joints
    tau_ff_nm: Joints
    kp_nm_per_rad: NonNegativeJoints
    kd_nms_per_rad: NonNegativeJoints


class DecisionRequest(Message):
    """The controller asks the human for the next decision (one per event trigger)."""

    episode: int = Field(ge=0)
    seed: int = Field(ge=0, description="the episode's task seed (a late joiner seeds from it)")
    request: int = Field(ge=0, description="request number within the episode")
    t_s: Finite = Field(ge=0, description="robot clock when asked [s]")
    ee_pos_m: Vec3 = Field(description="end-effector position the human sees")
    goal_m: Vec3
    primary_axis: Literal[0, 1, 2]
    human_model: HumanModel


class Intent(Message):
    """One decision of the human agent."""

    episode: int = Field(ge=0)
    request: int = Field(ge=-1, description="request answered, -1 when unsolicited")
    u_h: Literal[-1, 1] = Field(description="binary command on the primary axis")
    human_model: HumanModel = Field(description="radius chosen: 1 = E_big, 2 = E_small")
    radius_m: Finite = Field(gt=0, le=0.1, description="admission radius epsilon [m]")
    confidence: Finite = Field(ge=0, le=1, description="the source's probability of u_h")
    source: str = Field(min_length=1, max_length=64, description="the intent source's name")
    person: bool = Field(description="a person decided (a sensor), not a simulated human")
    decision_s: Finite = Field(ge=0, description="time the decision took [s]")
    correct: bool | None = Field(None, description="toward the goal (known in simulation)")

    @model_validator(mode="before")
    @classmethod
    def _recorded_before_person(cls, data: Any) -> Any:
        """Recordings made before ``person`` existed: the pad was the only person."""
        if isinstance(data, dict) and "person" not in data and "source" in data:
            return data | {"person": data["source"] == "sensor"}
        return data


class ModelChoice(Message):
    """The multi-model M_ij in force: human radius i and robot step vector j.

    The policy answers each DecisionRequest with a choice carrying its ``request``
    number (the human and the controller wait for it), and repeats the latest choice
    with ``request = -1`` for services that join late.
    """

    episode: int = Field(0, ge=0)
    request: int = Field(-1, ge=-1, description="DecisionRequest answered, -1 when periodic")
    human_model: HumanModel
    robot_model: RobotModel
    radius_m: Finite = Field(gt=0, le=0.1)
    steps_m: tuple[
        Annotated[float, Field(gt=0, le=0.1, allow_inf_nan=False)],
        Annotated[float, Field(gt=0, le=0.1, allow_inf_nan=False)],
        Annotated[float, Field(gt=0, le=0.1, allow_inf_nan=False)],
    ]
    posterior: tuple[Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)], ...] | None = Field(
        None, max_length=64
    )


class StepEvent(Message):
    """One micro-step of the controller."""

    episode: int = Field(ge=0)
    index: int = Field(ge=1)
    t_s: Finite = Field(ge=0, description="when the step was decided [s]")
    start_s: Finite = Field(ge=0, description="when its joint reference began [s]")
    trigger: Trigger
    u_h: Literal[-1, 1]
    radius_m: Finite = Field(gt=0)
    steps_m: Vec3
    dx_m: Vec3
    x_start_m: Vec3
    subgoal_m: Vec3
    goal_error_m: Finite = Field(ge=0)
    ik_compute_s: Finite = Field(ge=0)
    ik_latency_s: Finite = Field(ge=0)


class TaskGoal(Message):
    """A new episode: the arm starts at rest at ``q_start_rad`` and reaches ``goal_m``."""

    episode: int = Field(ge=1)
    seed: int = Field(ge=0)
    start_m: Vec3
    goal_m: Vec3
    q_start_rad: Joints


class GoalRefused(Message):
    """The arm cannot begin this episode: its start or goal lies beyond the arm's limits,
    or its start posture was not reached (the arm blocked on the way). The controller ends
    the episode as a hold with this reason and goes on. A goal refused for the arm's own
    state (stopped, faulted, still moving) is not sent: that episode waits for the arm."""

    episode: int = Field(ge=1)
    reason: str = Field(min_length=1, max_length=500)


class EpisodeResult(Message):
    """The metrics of one finished episode (same keys as ``dammrl reach --json``)."""

    episode: int = Field(ge=1)
    seed: int = Field(ge=0)
    trigger: Trigger
    model: tuple[HumanModel, RobotModel]
    success: bool = Field(description="the button pressed and held for the dwell time")
    reached: bool = Field(description="the paper's criterion ||x - x_g|| <= eps_g was met")
    outcome: Literal["success", "hold", "timeout", "skipped", "stopped"] = Field(
        description="stopped: an emergency stop ended the reach (a session does not count it)"
    )
    reason: str = Field(max_length=500)
    t_total_s: Finite
    t_step_mean_s: Finite | None = Field(description="None when no step was taken")
    final_error_m: Finite
    n_osc: int = Field(ge=0)
    n_osc_per_step: Finite | None = Field(description="None when no step was taken")
    jerk_isj: Finite
    sparc: Finite = Field(description="spectral arc length of the speed [-] (0: smoothest)")
    ldlj: Finite = Field(description="log dimensionless jerk of the speed [-] (higher: smoother)")
    human_error_rate: Finite
    n_steps: int = Field(ge=0)
    n_decisions: int = Field(ge=0)
    button_pressed: bool
    # the clinical kinematic set (None in recordings made before it existed)
    movement_time_s: Finite | None = Field(None, description="movement onset to offset [s]")
    peak_speed_m_s: Finite | None = Field(None, description="peak end-effector speed [m/s]")
    time_to_peak_speed_s: Finite | None = Field(None, description="onset to peak speed [s]")
    n_speed_peaks: int | None = Field(None, ge=0, description="speed-profile peaks")
    path_length_ratio: Finite | None = Field(
        None, description="path length / straight start-end distance [-] (1: straight)"
    )
    start_m: Vec3
    goal_m: Vec3
    last_state_stamp_ns: int | None = Field(
        None,
        ge=0,
        description="header stamp of the last robot state the reach took in (the arm's "
        "clock): a recording holds the reach whole once it holds that state (None in "
        "recordings made before it existed)",
    )


class SensorSample(Message):
    """One raw sample of the pressure sensor (semi-virtual mode)."""

    device_seq: int = Field(ge=0, description="sequence number sent by the device")
    raw: int = Field(description="ADC counts as sent by the device")
    pressure_kpa: Finite | None = Field(None, description="calibrated pressure [kPa]")
    level: Finite | None = Field(
        None, description="filtered pressure normalised by the calibration: 0 rest, 1 firm"
    )
    pressed: bool | None = Field(None, description="inside a press (hysteresis on)")


MAX_CHUNK_SAMPLES = 256
CHUNK_BYTES = 24_000
"""What a SignalChunk's samples may take on the wire (9 bytes a number): a sender puts
fewer samples in a message the more channels it has (``samples_per_chunk``)."""


def samples_per_chunk(channels: int) -> int:
    """How many samples of ``channels`` fit in one SignalChunk."""
    return max(1, min(MAX_CHUNK_SAMPLES, CHUNK_BYTES // (9 * (channels + 1))))


MAX_CHANNELS = 64


class SignalChunk(Message):
    """Raw samples of a wearable sensor's stream (LSL), as they came: kept so a session can
    be decoded again offline with another classifier."""

    stream: str = Field(min_length=1, max_length=200, description="the stream's name")
    rate_hz: Finite = Field(gt=0, le=20_000, description="the stream's nominal rate [Hz]")
    stamps_ns: list[Annotated[int, Field(ge=0)]] = Field(
        max_length=MAX_CHUNK_SAMPLES,
        description="each sample's time on the bus clock (the stream's own timestamps "
        "through LSL's clock correction) [ns since the Unix epoch]",
    )
    samples: list[
        Annotated[list[Annotated[float | None, Field(allow_inf_nan=False)]],
                  Field(min_length=1, max_length=MAX_CHANNELS)]
    ] = Field(
        max_length=MAX_CHUNK_SAMPLES,
        description="(samples, channels) in the stream's units; None where the stream sent "
        "a non-finite value",
    )  # fmt: skip
    missing: int = Field(
        0,
        ge=0,
        description="samples missing since the previous chunk of "
        "the stream (a gap in its timestamps, or dropped before the bus)",
    )
    clock_corrected_s: Finite = Field(0.0, description="added to the stream's own (LSL "
                                      "clock-synchronised) timestamps since they jumped [s]; "
                                      "0 unless its sender's clock jumped")  # fmt: skip

    @model_validator(mode="after")
    def _rectangular(self) -> SignalChunk:
        if len(self.samples) != len(self.stamps_ns):
            raise ValueError(f"{len(self.samples)} samples and {len(self.stamps_ns)} stamps")
        if len({len(row) for row in self.samples}) > 1:
            raise ValueError("every sample must have the same number of channels")
        return self


class IntentEvidence(Message):
    """One decision of a classifying intent source, acted on or not, with what it was
    decided from (the confidence and the features, for offline analysis)."""

    episode: int = Field(ge=0)
    request: int = Field(ge=-1, description="the open request it answered, -1 when none")
    source: str = Field(min_length=1, max_length=64)
    u_h: Literal[-1, 1]
    human_model: HumanModel = Field(description="radius from the contraction's length")
    confidence: Finite = Field(ge=0, le=1)
    onset_ns: int = Field(ge=0, description="when the contraction began, bus clock [ns]")
    decided_ns: int = Field(ge=0, description="the sample that completed it, bus clock [ns]")
    duration_s: Finite = Field(ge=0)
    windows: int = Field(ge=0, description="classifier windows it spans")
    features: tuple[Finite, ...] = Field(max_length=1024, description="mean window features")
    acted: bool = Field(description="it answered the open request (sent as Intent)")
    reason: str = Field("", max_length=200, description="why it was not acted on")


HealthState = Literal["ok", "holding", "degraded", "stopped"]


class Health(Message):
    """A service's periodic health report."""

    service: str = Field(min_length=1, max_length=64)
    state: HealthState = Field(
        description="stopped: an arm held by an emergency stop or a fault until released"
    )
    detail: str = Field("", max_length=2000)
    rejected: dict[Annotated[str, Field(max_length=200)], int] = Field(
        default_factory=dict, max_length=64, description="rejected messages per key and why"
    )
    rates_hz: dict[Annotated[str, Field(max_length=300)], Finite] = Field(
        default_factory=dict, max_length=64, description="publish rate per key"
    )
    uptime_s: Finite = Field(ge=0)
    peers: list[str] = Field(
        default_factory=list, max_length=64, description="services this one sees alive"
    )
    missing: dict[str, Finite] = Field(
        default_factory=dict,
        description="services this one saw alive that are gone: when it last saw each "
        "(Unix time) [s]",
    )


class EmergencyStop(Message):
    """Stop every arm (sim and robot) within one control period, until released. Latched:
    a stopped arm holds where it is with low gains (or torque off, by its settings) and
    takes no command; a release returns it to its ordinary hold, not to motion."""

    engaged: bool = Field(description="true: stop now; false: release a stop")
    reason: str = Field("", max_length=200, description="who stopped and why (for the record)")


class ComfortRating(Message):
    """The participant's comfort after a block of reaches, as they rated it on the
    participant display (the paper's S3 weighs "user comfort"): 1 very uncomfortable ...
    5 very comfortable."""

    participant: str = Field(
        max_length=16, pattern=r"^[A-Za-z0-9]*$", description="the pseudonymous id (or empty)"
    )
    block: str = Field(max_length=64, description="the protocol block just finished")
    trial: int = Field(ge=0, description="the session's last trial before the rating")
    rating: int = Field(ge=1, le=5, description="1 very uncomfortable ... 5 very comfortable")
    asked_s: float = Field(
        ge=0, allow_inf_nan=False, description="how long the question was shown [s]"
    )


OPERATOR = "operator"
"""``Intent.source`` of a decision the therapist made for the participant (a takeover):
no person's evidence (the posterior skips it)."""


ENDS_REACH = ("skip", "again", "end-block")
"""The therapist's acts that end the running reach (as skipped): ``skip`` (the trial
counts as skipped), ``again`` (it runs again), ``end-block`` (the rest of its block is
skipped). Each is recorded as itself: the record says which the therapist chose."""


class SessionControl(Message):
    """The therapist's hand on the running reach (the session console): ``pause`` holds
    the arm where its reference is and stops the reach's clock, ``resume`` goes on from
    there, ``skip``, ``again`` and ``end-block`` end the reach (``ENDS_REACH``); ``take``
    hands the decisions to the therapist (the participant's device is ignored),
    ``decide`` is the therapist's answer to the open request, ``give`` hands the
    decisions back. Applies to ``episode`` only (a late one changes nothing), but
    ``rebaseline``: a wearable's rest level measured afresh (the participant rests
    meanwhile; between blocks, whatever the episode). The emergency stop is
    ``EmergencyStop``, apart."""

    episode: int = Field(ge=1, description="the reach it applies to")
    action: Literal[
        "pause", "resume", "skip", "again", "end-block", "take", "give", "decide", "rebaseline"
    ]
    who: str = Field(min_length=1, max_length=32, description="the operator's id")
    why: str = Field("", max_length=200, description="the reason, for the record")
    u_h: Literal[-1, 1] | None = Field(None, description="decide: the command")
    human_model: HumanModel | None = Field(None, description="decide: the radius i")

    @model_validator(mode="after")
    def _decision_with_decide(self) -> SessionControl:
        decision = self.u_h is not None and self.human_model is not None
        if decision != (self.action == "decide") or (self.u_h is None) != (
            self.human_model is None
        ):
            raise ValueError("'decide' carries u_h and human_model, other actions neither")
        return self


class EpisodeRecorded(Message):
    """The recorder's acknowledgement that an episode is on disk: its result, the arm's
    states up to the one the result was decided from and the decisions the result counts
    (``complete``), written to ``file`` and synced. A session, and ``dammrl up --record``,
    wait for it before they stop the episode's stack; a later acknowledgement of the same
    episode supersedes an earlier, incomplete one."""

    episode: int = Field(ge=1, description="the episode whose result is on disk")
    file: str = Field(min_length=1, max_length=255, description="the recording's file name")
    result_seq: int = Field(ge=0, description="the result's sequence number (its publisher's)")
    states: int = Field(ge=0, description="the episode's robot states in the file so far")
    complete: bool = Field(
        description="the robot state the result was decided from (or the result names "
        "none) and the decisions it counts (its requests answered) are on disk too"
    )
    missing: str = Field("", max_length=500, description="what is not on disk (complete: empty)")
