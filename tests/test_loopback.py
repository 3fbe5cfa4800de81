"""estop.loopback.Daemon runs a daemon of either protocol version: v2 daemons (whose --help
lists --no-auth) will not start without --key-file or --no-auth; v1 daemons refuse both."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from estop.loopback import Daemon, DaemonError, auth_args

pytestmark = pytest.mark.timeout(60)

FAKE = '''
import socket, sys, time
v2 = {v2}
args = sys.argv[1:]
if "--help" in args:
    print("usage: estopd " + ("(--key-file PATH | --no-auth) " if v2 else "") + "[--can IFACE]")
    sys.exit(0)
auth = [a for a in args if a in ("--no-auth", "--key-file")]
if (v2 and len(auth) != 1) or (not v2 and auth):
    sys.stderr.write("estopd: error: bad options " + " ".join(args) + "\\n")
    sys.exit(2)
u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
u.bind(("127.0.0.1", 0))
t = socket.socket()
t.bind(("127.0.0.1", 0))
t.listen()
sys.stderr.write("start udp=%d tcp=%d\\n" % (u.getsockname()[1], t.getsockname()[1]))
sys.stderr.flush()
time.sleep(30)
'''


def fake(tmp_path: Path, v2: bool) -> list[str]:
    path = tmp_path / f"fake_estopd_v{2 if v2 else 1}.py"
    path.write_text(FAKE.format(v2=v2))
    return [sys.executable, str(path)]


@pytest.mark.parametrize("v2", [False, True])
def test_daemon_of_either_version_starts(tmp_path: Path, v2: bool) -> None:
    cmd = fake(tmp_path, v2)
    assert auth_args(cmd) == (["--no-auth"] if v2 else [])
    with Daemon(cmd) as d:
        assert d.udp_port > 0 and d.tcp_port > 0 and d.alive()
        assert ("--no-auth" in d.argv) == v2
    assert not d.alive()


def test_explicit_auth_is_used_as_given(tmp_path: Path) -> None:
    with Daemon(fake(tmp_path, True), auth=["--key-file", "/some/key"]) as d:
        assert d.argv[2:4] == ["--key-file", "/some/key"] and "--no-auth" not in d.argv
    d = Daemon(fake(tmp_path, True), auth=[])  # the v2 daemon refuses to start without
    with pytest.raises(DaemonError, match="did not start"):
        d.start()


def test_auth_args_of_a_missing_program(tmp_path: Path) -> None:
    assert auth_args([str(tmp_path / "nothing-here")]) == []
