"""``peel nachi-emulator``: serve NACHI-PEEL 1 (docs/nachi_protocol.md) over the plant.

    peel nachi-emulator [--host 127.0.0.1] [--port 48100] [--plant sim|plant] [--speed X]
                        [--seed S] [--fault KIND[:key=value,...]]... [--force-alarm N]
                        [--controller-id ID]

Runs until Ctrl-C or SIGTERM. The first line on stdout is ``listening on HOST:PORT ...`` (with
``--port 0`` the port the system picked); then one line per connection, task and event.
"""

from __future__ import annotations

import signal
import sys

from peel_msgs_py.cliargs import ArgumentParser, int_arg, nonnegative_int, positive_float, run_main
from peel_msgs_py.errors import PeelError
from peel_nachi_bridge import protocol as p

from .faults import KINDS, parse_fault


def build_parser() -> ArgumentParser:
    ap = ArgumentParser(prog="peel nachi-emulator", description=__doc__.split("\n\n")[0])
    ap.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    ap.add_argument("--port", type=int_arg(0, 65535), default=p.DEFAULT_PORT,
                    help=f"TCP port (default {p.DEFAULT_PORT}; 0 = any free port)")
    ap.add_argument("--plant", choices=("sim", "plant"), default="sim",
                    help="the simulator or the reality-gap plant (as peel graph --plant)")
    ap.add_argument("--speed", type=float, default=1.0,
                    help="X times real time; t on the line stays controller time (the bridge needs X > 1/3)")
    ap.add_argument("--seed", type=nonnegative_int, default=0,
                    help="task-sequence seed (as peel graph --seed)")
    ap.add_argument("--fault", action="append", default=[], metavar="KIND[:key=value,...]",
                    help=f"a fault for tests, repeatable; kinds: {', '.join(KINDS)} (docs/nachi.md)")
    ap.add_argument("--force-alarm", type=positive_float, default=25.0,
                    help="the controller's own force alarm, N (default 25)")
    ap.add_argument("--controller-id", default="EMU-MZ04", help="id sent in HELLO")
    return ap


def _terminate(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(argv: list[str]) -> int:
    from .emulator import ControllerEmulator, EmulatorOptions

    args = build_parser().parse_args(argv)
    if not p.TOKEN.match(args.controller_id):
        raise PeelError(f"--controller-id {args.controller_id!r} must be one token [A-Za-z0-9._:-]")
    opts = EmulatorOptions(host=args.host, port=args.port, source=args.plant, speed=args.speed,
                           seed=args.seed, controller_id=args.controller_id,
                           force_alarm_n=args.force_alarm,
                           faults=tuple(parse_fault(f) for f in args.fault))
    emu = ControllerEmulator(opts, log=lambda text: print(text, flush=True)).bind()
    signal.signal(signal.SIGTERM, _terminate)
    try:
        emu.serve()
    except KeyboardInterrupt:
        pass
    finally:
        emu.close()
    return 0


if __name__ == "__main__":
    sys.exit(run_main("peel nachi-emulator", main))
