"""estop.unit.daemon.Daemon starts a protocol-v2 daemon, which refuses to start without exactly
one of --key-file and --no-auth: --no-auth by default, --key-file with key_file."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from estop.unit.daemon import Daemon

pytestmark = pytest.mark.timeout(60)

FAKE = '''
import socket, sys, time
args = sys.argv[1:]
auth = [a for a in args if a in ("--no-auth", "--key-file")]
if len(auth) != 1:
    sys.stderr.write("estopd: error: exactly one of --key-file and --no-auth\\n")
    sys.exit(2)
u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
u.bind(("127.0.0.1", 0))
t = socket.socket()
t.bind(("127.0.0.1", 0))
t.listen()
sys.stderr.write("start udp=%d tcp=%d auth=%s\\n" % (u.getsockname()[1], t.getsockname()[1],
                                                     auth[0]))
sys.stderr.flush()
time.sleep(30)
'''


def fake(tmp_path: Path) -> list[str]:
    path = tmp_path / "fake_estopd.py"
    path.write_text(FAKE)
    return [sys.executable, str(path)]


def test_no_auth_by_default(tmp_path: Path) -> None:
    with Daemon(fake(tmp_path)) as d:
        assert d.udp_port > 0 and d.tcp_port > 0 and d.alive()
        assert "--no-auth" in d.argv and "--key-file" not in d.argv
        assert "auth=--no-auth" in d.log_lines[0]
    assert not d.alive()


def test_key_file(tmp_path: Path) -> None:
    with Daemon(fake(tmp_path), key_file="/some/key") as d:
        i = d.argv.index("--key-file")
        assert d.argv[i + 1] == "/some/key" and "--no-auth" not in d.argv
