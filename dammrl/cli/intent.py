"""``dammrl intent sources|calibrate|emulate``: where the human agent's decisions come from,
a person's calibration on a wearable sensor, and an emulated EMG armband on LSL."""

from __future__ import annotations

import argparse
import sys
import threading
from typing import TYPE_CHECKING

from dammrl.cli.common import (
    DEFAULT_CONNECT,
    Commands,
    add_bus_arguments,
    output_file,
    positive,
    print_err,
    print_out,
)
from dammrl_core.errors import ConfigurationError, Exit

if TYPE_CHECKING:
    from dammrl.devices.emulators.emg import EmgStream
    from dammrl.devices.emulators.emg_signal import EmgSynth
    from dammrl.devices.emulators.imu_signal import ImuSynth

EMULATED_STREAM = "dammrl-emg"


def register(commands: Commands) -> None:
    """Add ``intent`` and its actions."""
    intent = commands.add_parser("intent", help="the human agent's decisions: sources, "
                                 "a wearable's calibration, an emulated armband")  # fmt: skip
    actions = intent.add_subparsers(required=True, metavar="ACTION")
    helptext = (
        "the intent sources installed (built-in and from packages); choose one with "
        "DAMMRL_INTENT_SOURCE"
    )
    sources = actions.add_parser("sources", help=helptext, description=helptext)
    sources.set_defaults(handler=_sources)
    _add_calibrate(actions)
    _add_emulate(actions)
    helptext = (
        "measure the participant's rest level afresh on the running stack's wearable "
        "(they rest for DAMMRL_LSL_REBASELINE_S, 3 s; between blocks, no calibration)"
    )
    rebaseline = actions.add_parser("rebaseline", help=helptext, description=helptext)
    add_bus_arguments(rebaseline, f"the stack's endpoint (default {DEFAULT_CONNECT})")
    rebaseline.add_argument("--who", default="therapist", help="the operator's id (recorded)")
    rebaseline.set_defaults(handler=_rebaseline)


def _add_calibrate(actions: Commands) -> None:
    calibrate = actions.add_parser(
        "calibrate",
        help="calibrate a person on a wearable sensor's LSL stream (cued blocks)",
        description="Cue blocks of trials (rest, -1, +1) on the terminal and on the LSL "
        "marker stream 'dammrl-cues:STREAM', record the stream, train the person's classifier, "
        "cross-validate it leave-one-block-out; a calibration whose classes do not separate "
        "is refused with the reason (--force keeps it anyway).",
    )
    calibrate.add_argument("--source", choices=["lsl"], default="lsl", help="the source kind")
    calibrate.add_argument("--stream", required=True, help="the LSL stream's name")
    calibrate.add_argument("--source-id", help="the stream's source id (several of one name)")
    calibrate.add_argument("--out", type=output_file(".json"), required=True,
                           help="the calibration file (DAMMRL_LSL_CALIBRATION_FILE)")  # fmt: skip
    calibrate.add_argument("--report", type=output_file(".md"),
                           help="a markdown report, its confusion matrix beside it")  # fmt: skip
    calibrate.add_argument("--participant", help="a pseudonymous id (never a name)")
    calibrate.add_argument("--blocks", type=int, default=4, help="blocks of 3 trials (>= 2)")
    calibrate.add_argument("--trial-s", type=positive, default=3.0, help="trial length [s]")
    calibrate.add_argument("--relax-s", type=positive, default=1.5, help="pause after a trial [s]")
    calibrate.add_argument("--features", choices=["auto", "emg", "imu"], default="auto",
                           help="the feature set: EMG (Hudgins) or IMU (orientation and "
                           "movement); auto: from the stream's type")  # fmt: skip
    calibrate.add_argument("--mains", choices=["50", "60", "off"], default="50",
                           help="EMG: the mains frequency notched out before the features "
                           "(50 Hz: Europe, Asia, Africa; 60 Hz: the Americas)")  # fmt: skip
    calibrate.add_argument("--force", action="store_true", help="save a refused calibration")
    calibrate.set_defaults(handler=_calibrate)


def _add_emulate(actions: Commands) -> None:
    emulate = actions.add_parser(
        "emulate",
        help="an emulated EMG armband on LSL (until Ctrl-C)",
        description="A synthetic forearm's EMG (microvolts) streamed on LSL in real time. "
        "Faults from stdin, one per line: flat CH, clip CH, back CH, lose S, nan S, jump S, "
        "twin, untwin, dc MICROVOLTS, gain FACTOR.",
    )
    emulate.add_argument("--stream", default=EMULATED_STREAM, help="the LSL stream's name")
    emulate.add_argument("--source-id", default="dammrl-emulated-emg",
                         help="the stream's LSL source id ('' for none, as many amplifier "
                         "programs send it)")  # fmt: skip
    emulate.add_argument("--pattern", choices=["patient", "cued", "rest"], default="patient",
                         help="patient: answers the stack's decision requests; cued: follows "
                         "`dammrl intent calibrate`; rest: nobody moves")  # fmt: skip
    emulate.add_argument("--kind", choices=["emg", "imu"], default="emg",
                         help="an 8-channel EMG armband, or a 6-axis wrist IMU (a flexed or "
                         "extended wrist)")  # fmt: skip
    emulate.add_argument("--noise", choices=["low", "medium", "high"], default="medium",
                         help="electrode noise, crosstalk, artefacts, drift (IMU: sensor "
                         "noise, the arm's sway)")  # fmt: skip
    emulate.add_argument("--channels", type=int, default=8, help="EMG channels (1-64)")
    emulate.add_argument("--rate", type=positive,
                         help="samples per second (default 1000 EMG, 100 IMU)")  # fmt: skip
    emulate.add_argument("--patient-model", type=int, choices=[1, 2], default=2,
                         help="patient: 1 hurried (quick contractions, E_big), 2 careful "
                         "(held, E_small)")  # fmt: skip
    emulate.add_argument("--seed", type=int, default=0, help="the signal and the patient")
    add_bus_arguments(
        emulate,
        "patient: the stack's endpoint (default: the local `dammrl up` "
        f"that reads this --stream, else {DEFAULT_CONNECT})",
    )
    emulate.add_argument("--seconds", type=positive, help="stop after this long")
    emulate.set_defaults(handler=_emulate)


def _sources(args: argparse.Namespace) -> int:
    from dammrl_core.intent.source import source_plugins

    for name, origin in source_plugins().items():
        print_out(f"{name:16s} {origin}")
    return Exit.OK


def _calibrate(args: argparse.Namespace) -> int:
    from dammrl.devices.wearable import (
        Protocol,
        calibrate,
        feature_set_of,
        find_stream,
        write_report,
    )
    from dammrl_core.intent.emg.calibration import save_calibration

    if args.blocks < 2:
        raise ConfigurationError(f"--blocks {args.blocks}: 2 at least (leave-one-block-out)")
    info = find_stream(args.stream, args.source_id)
    print_out(f"calibrating on {info.name()!r}: {info.channel_count()} channels at "
              f"{info.nominal_srate():g} Hz from {info.hostname()}")  # fmt: skip
    protocol = Protocol(args.blocks, args.trial_s, args.relax_s)
    kind = args.features if args.features != "auto" else feature_set_of(info)
    mains = 0 if args.mains == "off" else int(args.mains)
    calibration, refused = calibrate(info, protocol, print_out, args.participant, kind,
                                     mains)  # type: ignore[arg-type]  # fmt: skip
    cv = calibration.cross_validation
    print_out(f"leave-one-block-out: accuracy {cv.accuracy:.3f}, active error rate "
              f"{cv.active_error_rate:.3f}, instability {cv.instability:.3f}, rejection rate "
              f"{cv.rejection_rate:.3f}")  # fmt: skip
    if args.report is not None:
        print_out(f"report: {write_report(calibration, refused, args.report)}")
    if refused and not args.force:
        print_err(f"dammrl: calibration refused, not saved: {refused}")
        return Exit.FAILED
    print_out(f"saved {save_calibration(calibration, args.out)}"
              + (f" (refused, kept by --force: {refused})" if refused else ""))  # fmt: skip
    return Exit.OK


def _rebaseline(args: argparse.Namespace) -> int:
    from dammrl.cli.common import bus_settings
    from dammrl.devices.wearable import REBASELINE_WAIT_S, rebaseline

    if not 1 <= len(args.who) <= 32:
        raise ConfigurationError(f"--who {args.who!r}: 1-32 characters")
    said = rebaseline(bus_settings(args), args.who)
    if said is None:
        print_err(f"dammrl: no intent service measuring a rest level confirmed within "
                  f"{REBASELINE_WAIT_S:g} s (is the stack up, with a wearable?)")  # fmt: skip
        return Exit.FAILED
    print_out(f"intent: {said}")
    return Exit.OK


def _emulate(args: argparse.Namespace) -> int:
    from dammrl.cli.sensor import stop_after
    from dammrl.devices.emulators.emg import EmgStream
    from services.common.runtime import stop_on_signals

    if not 1 <= args.channels <= 64:
        raise ConfigurationError(f"--channels {args.channels}: 1-64")
    if len(args.source_id) > 200:
        raise ConfigurationError(
            f"--source-id: at most 200 characters, {len(args.source_id)} given"
        )
    stop = stop_on_signals()
    stop_after(stop, args.seconds)
    synth = _synth(args)
    model = synth.model
    with EmgStream(args.stream, synth, args.source_id) as stream:
        print_out(f"emulated {stream.stream_type} on LSL stream {args.stream!r}: "
                  f"{model.channels} channels at {model.rate_hz:g} Hz, {args.noise} noise; "
                  "Ctrl-C stops")  # fmt: skip
        _faults_from_stdin(stream, stop)
        if args.pattern == "patient":
            _patient(args, stream, stop)
        elif args.pattern == "cued":
            print_out(f"followed {stream.follow_cues(stop)} cues")
        else:
            stop.wait()
        print_out(f"sent {stream.sent} samples")
    return Exit.OK


def _synth(args: argparse.Namespace) -> EmgSynth | ImuSynth:
    from dataclasses import replace

    from dammrl.devices.emulators.emg_signal import EmgSynth, model_named
    from dammrl.devices.emulators.imu_signal import IMU_NOISE_LEVELS, ImuSynth

    if args.kind == "imu":
        model = IMU_NOISE_LEVELS[args.noise]
        return ImuSynth(replace(model, rate_hz=args.rate or model.rate_hz), args.seed)
    rate = args.rate or 1000.0
    return EmgSynth(model_named(args.noise, channels=args.channels, rate_hz=rate), args.seed)


def _patient(args: argparse.Namespace, stream: EmgStream, stop: threading.Event) -> None:
    from dammrl.cli.sensor import answer_while_joined
    from dammrl.devices.emulators.patient import SimulatedPatient
    from services.common.runs import run_reading

    patient = SimulatedPatient(stream, args.patient_model, seed=args.seed)
    print_out(f"simulated patient (M_{args.patient_model}) answering decision requests")
    said = False
    while not stop.is_set():  # without --connect/--bus-port: the run that reads this stream
        said = answer_while_joined(args, patient, stop, said,
                                   lambda: run_reading(stream=args.stream))  # fmt: skip
    print_out(f"answered {patient.answered} requests")


def _faults_from_stdin(stream: EmgStream, stop: threading.Event) -> None:
    """Read fault lines from stdin on a thread (nothing when stdin is closed)."""

    def read() -> None:
        for line in sys.stdin:
            if stop.is_set():
                return
            print_err(stream.fault(line))

    threading.Thread(target=read, daemon=True).start()
