"""``estop remote``: plays the tablet, from the keys of a terminal or from a script.

The parts, one job each:

- :mod:`estop.client.sender` -- :class:`~estop.client.sender.Remote`: the UDP sender thread
  and the TCP stop channel (the library the demo, benchmarks and HIL harness use);
- :mod:`estop.remote.script` -- the script language (``--script``, ``--script-file``);
- :mod:`estop.remote.keys` -- the interactive terminal (keys, status line);
- :mod:`estop.remote.gamepad` -- a game controller with a real dead-man (``--gamepad``; the
  mapping of its events in :mod:`estop.remote.gamepadmap`);
- :mod:`estop.remote.touch` -- a touch page served to a phone or tablet, with a real dead-man
  (``--touch``: the page's hop, its server and its messages);
- this module -- the command line: options, the link model from them, the run and its summary.

The keyboard is NOT a dead-man switch: a terminal sees a key pressed but never released, so the
space bar toggles the hold, and the packets go on while nobody touches anything. A real
dead-man (held trigger, released: lift at once) is ``estop remote --gamepad``, or a finger
on the page of ``estop remote --touch``.

Exit code (the table of every command: :data:`estop.errors.EXIT_CODES`): 0 done, 1 an
``expect`` failed, 2 usage error or bad script, 3 the stop channel failed (connection refused
or closed, timeout, malformed reply), the game controller was not found or went away, or
(--touch) the unit did not answer at the start or the address cannot be listened on, 4 the
script or key file cannot be read, 5 a needed extra (evdev for --gamepad, aiohttp and segno
for --touch) is not installed.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from estop.client.button import DEFAULT_STOP_DEADLINE
from estop.client.channel import StopChannelError
from estop.client.sender import MAX_RATE_HZ, MIN_RATE_HZ, Remote, check_rate, lift_line
from estop.commands.options import (
    add_time_option,
    non_negative_float,
    parse_listen,
    positive_float,
)
from estop.commands.output import err, out
from estop.commands.settings import add_settings, key_from_args
from estop.errors import EXIT_OK, EXIT_REFUSED, ConnectionFailure, FileFailure, UsageError
from estop.model.wifi import IDEAL, WIFI, LinkConfig
from estop.protocol import tcp
from estop.remote.script import ExpectFailed, ScriptError, ScriptRunner, Step, parse_script
from estop.remote.touch import DEFAULT_LISTEN as TOUCH_LISTEN

__all__ = ["DESCRIPTION", "EPILOG", "add_parser", "link_config", "rate_arg", "run"]

DESCRIPTION = """\
Play the tablet: send control packets over UDP while held (a finger on the screen), and
STOP/RELEASE/STATUS over the TCP stop channel; keys in a terminal, or a script.

The keyboard's hold is a TOGGLE, NOT a dead-man: a terminal cannot see a key being
released, so packets go on until space is pressed again. For a real dead-man (let go
of the trigger: lift at once) use --gamepad."""
EPILOG = """\
script (--script TEXT or --script-file FILE): commands separated by ';' or new lines,
'#' starts a comment, times in seconds:
  hold [T]        finger down: start sending (then wait T)
  lift [T]        finger up: stop sending, send the lift datagrams (then wait T)
  wait T          wait
  gas X           gas_brake X (-1.0 full brake .. 1.0 full gas)
  steer X         steering X (-1.0 left .. 1.0 right)
  gear G          park, reverse, neutral, drive
  signal S        off, left, right, both
  horn on|off
  drive X [T]     gear drive and gas X; with T: after T seconds gas back to 0
  neutral         gas 0, steering 0, gear neutral
  rate HZ         change the send rate (0.1..1000)
  stop            the stop button: stop datagram + TCP STOP, tried again until an
                  answer or --stop-deadline-ms; prints the reply and the attempts
  release | status             TCP request, prints the reply
  expect W...     the last reply must match every word (ack nak stopped armed slowing
                  none boot tcp_stop udp_timeout fault lift unknown_msg_id no_live_link
                  not_neutral not_authenticated link_degraded link_ok), else exit 1
example: --script "hold 1.0; release; expect ack armed; drive 0.3 2.0; lift; wait 0.1;
  status; expect stopped lift; stop"

the end of a hold (lift, the space key, the end of the script, q, Ctrl-C) sends a
lift datagram at once and twice more 10 ms apart (spec section 8): the unit stops
with reason lift without waiting for its timeout

gamepad (--gamepad): hold the dead-man (left trigger) to send, let go: lift at once;
left stick steering, right stick gas (up) / brake (down), B stop, START release,
SELECT status, Y next gear, X horn, D-pad turn signal; a pad unplugged lifts (exit 3)

touch (--touch [--listen ADDR:PORT]): serve a page; a finger on its drive area is the
dead-man (steering across, gas up / brake down, neutral in the middle), STOP, RELEASE,
gear; the last finger leaving, the page hidden or its connection closing lifts at once;
a page that stops sending goes silent (the unit slows at S, stops at T). The address is
printed first, with a pairing token the page needs to drive (docs/REMOTE.md)

keys (terminal): space hold/lift, s stop, r release, t status, arrows gas/steering,
n neutral, g next gear, h horn, 0-3 turn signal, q quit
the space bar is a TOGGLE, NOT a dead-man: a terminal cannot see a key released, so
the packets go on until space is pressed again; a real dead-man: --gamepad

exit codes (as every estop command, estop --help): 0 done, 1 an expect failed,
2 usage error or bad script, 3 stop channel failed (refused, closed, timeout,
malformed reply; for stop: no answer by --stop-deadline-ms), 4 file cannot be read"""


def rate_arg(text: str) -> float:
    """argparse type of ``--rate-hz``."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    try:
        return check_rate(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


# ------------------------------------------------------------------------------ the CLI

def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = sub.add_parser("remote", help="play the tablet (UDP control packets, TCP stop "
                            "button)", description=DESCRIPTION, epilog=EPILOG,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.set_defaults(handler=run)
    add_settings(parser, "host", "udp_port", "tcp_port", "rate_hz", "stop_id", "key_file",
                 "remote_id", aliases={"rate_hz": ["--rate"]}, parse={"rate_hz": rate_arg},
                 help={"rate_hz": f"control packets per second while held, {MIN_RATE_HZ:g}.."
                                  f"{MAX_RATE_HZ:g}"})
    parser.add_argument("--wifi", action="store_true",
                        help=f"link like the original Wi-Fi: {WIFI.loss * 100:g} %% loss, "
                             f"bursts of {WIFI.burst:g}, {WIFI.delay * 1000:g}+0..."
                             f"{WIFI.jitter * 1000:g} ms delay (options below override)")
    parser.add_argument("--loss-pct", dest="loss", type=non_negative_float, default=None,
                        metavar="PCT", help="UDP packets lost, percent (default 0)")
    parser.add_argument("--loss", dest="loss", type=non_negative_float,
                        default=argparse.SUPPRESS, help=argparse.SUPPRESS)  # the older name
    parser.add_argument("--burst", type=positive_float, default=None, metavar="N",
                        help="mean number of packets lost in a row (default 1)")
    parser.add_argument("--delay-ms", type=non_negative_float, default=None, metavar="MS",
                        help="one-way delay (default 0)")
    parser.add_argument("--jitter-ms", type=non_negative_float, default=None, metavar="MS",
                        help="extra random delay 0..MS (default 0)")
    parser.add_argument("--seed", type=int, default=None, help="seed of the link model")
    add_time_option(parser, "reply-timeout", "timeout", 2.0,
                    "wait this long for connect and reply",
                    ms_aliases=["--timeout-ms"], s_aliases=["--timeout"])
    add_time_option(parser, "stop-deadline", "stop_deadline", DEFAULT_STOP_DEADLINE,
                    "the stop button tries again (fresh connection, another stop datagram) "
                    "until an ACK or this time passes")
    parser.add_argument("--legacy", action="store_true",
                        help="send the older 16-byte packets (no horn; not with a key)")
    script = parser.add_mutually_exclusive_group()
    script.add_argument("--script", metavar="TEXT", help="run this script instead of keys")
    script.add_argument("--script-file", metavar="FILE", help="run the script in FILE")
    script.add_argument("--gamepad", nargs="?", const="", metavar="DEVICE",
                        help="a game controller is the remote, with a real dead-man (hold "
                             "the left trigger to drive; needs the gamepad extra): "
                             "/dev/input/eventN, or the first one found")
    script.add_argument("--touch", action="store_true",
                        help="serve a touch page and drive from a phone, tablet or touch "
                             "laptop, with a real dead-man (a finger on the page; needs the "
                             "touch extra); the address (with its pairing token) is printed "
                             "first")
    parser.add_argument("--listen", metavar="ADDR:PORT", default=None,
                        help=f"--touch: serve the page here (default {TOUCH_LISTEN}: this "
                             "machine only; another address serves the network, an explicit "
                             "choice, with a QR code of the address; port 0: any free)")
    parser.add_argument("--deadman", metavar="CONTROL", default=None,
                        help="--gamepad: the dead-man control, e.g. BTN_TL (default: the "
                             "first of ABS_Z, BTN_TL2, BTN_TL the pad has)")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="script mode: print only replies and the summary")


def link_config(args: argparse.Namespace) -> LinkConfig:
    base = WIFI if args.wifi else IDEAL
    cfg = LinkConfig(
        loss=base.loss if args.loss is None else args.loss / 100.0,
        burst=base.burst if args.burst is None else args.burst,
        delay=base.delay if args.delay_ms is None else args.delay_ms / 1000.0,
        jitter=base.jitter if args.jitter_ms is None else args.jitter_ms / 1000.0,
    )
    try:
        cfg.validate()
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return cfg


def _summary(remote: Remote) -> str:
    s = remote.stats
    return (f"summary: {s.sent} packets sent, {s.delivered} delivered, {s.lost} lost "
            f"({s.loss_fraction * 100:.1f} %), longest loss burst "
            f"{remote.link.stats.longest_burst}, {s.requests} TCP replies, "
            f"{s.lift_datagrams} lift datagrams")


def run(args: argparse.Namespace) -> int:
    cfg = link_config(args)
    try:
        tcp.check_stop_id(args.stop_id)
    except ValueError as exc:
        raise UsageError(f"--stop-id: {exc}") from None
    text: str | None = args.script
    if args.script_file is not None:
        try:
            with open(args.script_file, encoding="utf-8") as f:
                text = f.read()
        except (OSError, UnicodeDecodeError) as exc:
            why = exc.strerror if isinstance(exc, OSError) else "not UTF-8 text"
            raise FileFailure(f"--script-file {args.script_file}: {why or exc}") from None
    steps: list[Step] | None = None
    if text is not None:
        try:
            steps = parse_script(text)
        except ScriptError as exc:
            raise UsageError(f"script: {exc}") from None
    elif args.gamepad is None and not args.touch and not sys.stdin.isatty():
        raise UsageError("interactive mode needs a terminal; use --script or --script-file")
    if args.deadman is not None and args.gamepad is None:
        raise UsageError("--deadman: only with --gamepad")
    if args.listen is not None and not args.touch:
        raise UsageError("--listen: only with --touch")
    listen = parse_listen(args.listen or TOUCH_LISTEN) if args.touch else None
    key = key_from_args(args)
    if key is not None and args.legacy:
        raise UsageError("--legacy: with --key-file the remote sends 60-byte packets")
    try:
        remote = Remote(args.host, args.udp_port, args.tcp_port, rate_hz=args.rate_hz, link=cfg,
                        seed=args.seed, stop_id=args.stop_id, tcp_timeout=args.timeout,
                        stop_deadline=args.stop_deadline, legacy=args.legacy, key=key,
                        remote_id=args.remote_id, paced=not args.touch)
    except OSError as exc:
        raise ConnectionFailure(f"cannot open a UDP socket: {exc}") from None
    code = EXIT_OK
    quiet: bool = args.quiet

    def log(line: str) -> None:
        if not quiet or " -> " in line:
            out(line)

    with remote:
        try:
            # each mode's module when it runs (the touch page's server loads asyncio)
            if args.gamepad is not None:
                from estop.remote.gamepad import run_gamepad
                code = run_gamepad(remote, args.gamepad or None, args.deadman, log)
            elif listen is not None:
                from estop.remote.touch.run import run_touch
                code = run_touch(remote, *listen, log=log, say=out, warn=err)
            elif steps is None:
                from estop.remote.keys import run_interactive
                run_interactive(remote, out)
            else:
                code = _run_script(remote, steps, log)
        finally:
            # however the run ends (the script's end, q, Ctrl-C, a failed stop channel), a
            # hold still on ends here, and the unit is told at once
            if remote.held:
                log(f"end of run: {lift_line(remote)}")
    out(_summary(remote))
    return code


def _run_script(remote: Remote, steps: list[Step], log: Callable[[str], None]) -> int:
    try:
        ScriptRunner(remote, log=log).run(steps)
    except ExpectFailed as exc:
        out(f"expect failed: {exc}")
        return EXIT_REFUSED
    except StopChannelError as exc:
        raise ConnectionFailure(str(exc)) from None
    return EXIT_OK
