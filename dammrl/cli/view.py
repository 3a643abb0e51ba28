"""``dammrl view``: the stack (or a recording) live in Foxglove."""

from __future__ import annotations

import argparse
import importlib.util
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from dammrl.cli.common import (
    CONNECT_HELP,
    Commands,
    add_bus_arguments,
    bus_settings,
    output_file,
    print_err,
)

if TYPE_CHECKING:
    from dammrl.views.viewer import FoxgloveServer, SceneTranslator


def register(commands: Commands) -> None:
    """Add ``view``."""
    view = commands.add_parser(
        "view",
        help="serve the stack or a recording to Foxglove (3D arm, goal, subgoal, plots)",
        description="A Foxglove WebSocket server: open Foxglove, connect to "
        "ws://HOST:PORT, and import the layout (docs/foxglove_layout.json, or --layout-out).",
    )
    view.add_argument("--recording", type=Path, metavar="MCAP",
                      help="play a recording instead of the live bus")  # fmt: skip
    view.add_argument("--rate", type=float, default=1.0,
                      help="with --recording: playback speed (0: as fast as possible)")  # fmt: skip
    view.add_argument("--once", action="store_true",
                      help="with --recording: play it once and exit (default: wait for a "
                      "viewer, play, and again while one is connected, until Ctrl-C)")  # fmt: skip
    view.add_argument("--host", default="127.0.0.1",
                      help="address to serve on (default 127.0.0.1; 0.0.0.0: all)")  # fmt: skip
    view.add_argument("--port", type=int, default=8765, help="WebSocket port (default 8765)")
    view.add_argument("--max-hz", type=float, default=30.0,
                      help="messages per topic and second (default 30, max 60)")  # fmt: skip
    view.add_argument("--layout-out", type=output_file(".json"), metavar="JSON",
                      help="write the Foxglove layout to this file and exit")  # fmt: skip
    add_bus_arguments(view, CONNECT_HELP)
    view.set_defaults(handler=_view)


def _view(args: argparse.Namespace) -> int:
    """Translate until Ctrl-C (or the recording's end); print where to connect."""
    from dammrl_core.errors import UsageError
    from dammrl_core.robot import RobotDescription
    from services.common.runtime import stopping_on_signals

    if not 0 < args.max_hz <= 60:
        raise UsageError(f"--max-hz must be in (0, 60], got {args.max_hz}")
    if args.recording is not None and not args.recording.is_file():
        raise UsageError(f"no such recording: {args.recording}")
    if importlib.util.find_spec("foxglove") is None:
        raise UsageError("dammrl view needs foxglove-sdk: pip install 'dammrl[view]'")
    from dammrl.views.viewer import FoxgloveServer, SceneTranslator, bus_messages, layout

    if args.layout_out is not None:
        args.layout_out.write_text(layout() + "\n")
        print(args.layout_out)
        return 0
    robot = RobotDescription.from_urdf()
    server = FoxgloveServer(robot, args.host, args.port)
    print_err(f"Foxglove: open ws://{args.host}:{server.port}; import the layout from "
              "`dammrl view --layout-out layout.json`")  # fmt: skip
    translator = SceneTranslator(robot, server.log, args.max_hz)
    try:
        with stopping_on_signals() as stop:
            if args.recording is None:
                for message, t_ns in bus_messages(bus_settings(args), stop, print_err):
                    translator.feed(message, t_ns)
            else:
                _play(args.recording, args.rate, args.once, server, translator, stop)
    finally:
        server.stop()
    return 0


def _play(recording: Path, rate: float, once: bool, server: FoxgloveServer,
          translator: SceneTranslator, stop: threading.Event) -> None:  # fmt: skip
    """Play the recording each time a viewer is subscribed, its times running on from one
    play to the next (a viewer's plots never see time go back)."""
    from dammrl.views.viewer import recording_messages

    offset, plays = 0, 0
    while not stop.is_set():
        if not server.clients.any.is_set():
            print_err("waiting for a viewer to subscribe (Ctrl-C to stop)")
            while not server.clients.any.wait(0.2):
                if stop.is_set():
                    return
        first = last = None
        for message, t_ns in recording_messages(recording, rate, stop):
            first = t_ns if first is None else first
            last = t_ns
            translator.feed(message, t_ns + offset)
        plays += 1
        print_err(f"played {recording} ({plays}x)")
        if once or first is None or last is None:
            return
        offset += last - first + 1_000_000_000  # a second's gap between plays
