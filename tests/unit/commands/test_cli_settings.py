"""The common settings of every ``estop`` command: command line > environment > configuration
file > default, a bad value named by its source in one line, and the per-installation remote
id made on first use with a key. Against the real estopd on loopback where a unit answers."""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from cli_util import run_cli
from estop import cli
from estop.client.channel import StopChannel
from estop.client.identity import Identity, MessageCounter
from estop.client.keyfile import write_key_file
from estop.commands.configfile import ConfigFile, config_path
from estop.commands.settings import COMMON_SETTINGS, resolve_settings
from estop.protocol import tcp, udp
from estop.unit.daemon import Daemon

pytestmark = pytest.mark.timeout(60)
LOCAL = "127.0.0.1"


def error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("estop: error: "), err
    return lines[0]


@pytest.fixture
def config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An empty config home; returns the config file's path (not yet written)."""
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    path = tmp_path / "xdg" / "estop" / "config.toml"
    assert config_path() == path
    return path


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def parse(argv: list[str], environ: dict[str, str], cfg: Path) -> object:
    args = cli.build_parser().parse_args(argv)
    resolve_settings(args, environ, ConfigFile(cfg, COMMON_SETTINGS))
    return args


# ------------------------------------------------------------------------------ precedence

def test_command_line_over_environment_over_config_over_default(tmp_path: Path) -> None:
    cfg = write(tmp_path / "c.toml", 'host = "10.0.0.9"\nudp_port = 6000\ntcp_port = 6001\n'
                                     'rate_hz = 20\nstop_id = 0x12345678\n')
    env = {"ESTOP_UDP_PORT": "7000", "ESTOP_RATE_HZ": "25"}
    a = parse(["remote", "--udp-port", "8000", "--script", "wait 0"], env, cfg)
    assert (a.host, a.udp_port, a.tcp_port, a.rate_hz, a.stop_id) == \
        ("10.0.0.9", 8000, 6001, 25.0, 0x12345678)  # type: ignore[attr-defined]
    a = parse(["remote", "--script", "wait 0"], env, cfg)
    assert a.udp_port == 7000  # type: ignore[attr-defined]
    a = parse(["remote", "--host", "h", "--script", "wait 0"], {}, tmp_path / "none.toml")
    assert (a.udp_port, a.tcp_port, a.rate_hz, a.stop_id, a.remote_id) == \
        (udp.DEFAULT_PORT, tcp.DEFAULT_PORT, 50.0, tcp.DEFAULT_STOP_ID, 1)  # type: ignore


def test_older_names_are_the_same_settings(tmp_path: Path) -> None:
    none = tmp_path / "none.toml"
    a = parse(["status", "--host", "h", "--port", "6100"], {}, none)
    assert a.tcp_port == 6100  # type: ignore[attr-defined]
    a = parse(["remote", "--host", "h", "--rate", "10", "--script", "wait 0"], {}, none)
    assert a.rate_hz == 10.0  # type: ignore[attr-defined]
    a = parse(["link", "x", "--port", "6200"], {"ESTOP_UDP_PORT": "6300"}, none)
    assert a.udp_port == 6200  # type: ignore[attr-defined]


def test_status_from_environment_and_config_against_estopd(config: Path, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str],
                                                          estopd: str) -> None:
    """A team sets the unit once: `estop status` with no option at all reaches it."""
    exe = estopd
    key_path = tmp_path / "key"
    write_key_file(key_path)  # a new random key, mode 0600
    with Daemon([exe], key_file=str(key_path)) as d:
        write(config, f'host = "{LOCAL}"\ntcp_port = {d.tcp_port}\nkey_file = "../../key"\n'
                      f'remote_id = 77\n')
        code, out, err = run_cli(capsys, "status")
        assert (code, err) == (0, ""), out
        assert out.startswith("ACK seq=1 state=STOPPED reason=boot")
        # the environment beats the file: a wrong port there is what the tool uses
        monkeypatch.setenv("ESTOP_TCP_PORT", str(free_tcp_port()))
        code, out, err = run_cli(capsys, "status", "--reply-timeout-ms", "300")
        assert code == 3 and "cannot connect" in error_line(err)
        # and the command line beats the environment
        code, out, err = run_cli(capsys, "status", "--tcp-port", str(d.tcp_port))
        assert code == 0, err


def free_tcp_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind((LOCAL, 0))
        return int(s.getsockname()[1])


# ------------------------------------------------------------------------------ bad values

@pytest.mark.parametrize("env, text, named", [
    ({"ESTOP_UDP_PORT": "abc"}, "", "ESTOP_UDP_PORT=abc: not a port number"),
    ({"ESTOP_TCP_PORT": "70000"}, "", "ESTOP_TCP_PORT=70000: port 70000 out of range"),
    ({"ESTOP_REMOTE_ID": "-1"}, "", "ESTOP_REMOTE_ID=-1"),
    ({"ESTOP_STOP_ID": "1"}, "", "ESTOP_STOP_ID=1"),
    ({"ESTOP_RATE_HZ": "0"}, "", "ESTOP_RATE_HZ=0"),
    ({}, 'udp_port = "x"\n', "config.toml: udp_port: not a port number"),
    ({}, "tcp_port = true\n", "config.toml: tcp_port: expected a number or a string"),
    ({}, "udp-port = 5700\n", "config.toml: unknown setting 'udp-port'"),
    ({}, "host = \n", "config.toml: not valid TOML"),
])
def test_a_bad_value_names_its_source_in_one_line(env: dict[str, str], text: str, named: str,
                                                  config: Path,
                                                  monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    if text:
        write(config, text)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    commands = [["remote", "--host", LOCAL, "--script", "wait 0"]]
    if "UDP" not in named and "udp" not in named and "RATE" not in named:
        commands.append(["status", "--host", LOCAL])  # status has no UDP port and no rate
    for argv in commands:
        code, out, err = run_cli(capsys, *argv)
        assert code == 2 and out == "", err
        assert named in error_line(err), err


def test_no_host_anywhere_says_where_to_set_it(config: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    for cmd in ("stop", "lift", "status", "release"):
        code, _, err = run_cli(capsys, cmd)
        line = error_line(err)
        assert code == 2 and "--host" in line and "ESTOP_HOST" in line and str(config) in line


def test_key_file_from_config_is_relative_to_it(config: Path, tmp_path: Path) -> None:
    write(config, 'key_file = "k"\nremote_id = 3\n')
    a = parse(["status", "--host", "h"], {}, config)
    assert a.key_file == str(config.parent / "k")  # type: ignore[attr-defined]


# ------------------------------------------------------------------------- the remote id

def test_remote_id_is_made_once_per_installation_with_a_key(config: Path, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str],
                                                            estopd: str) -> None:
    exe = estopd
    key_path = tmp_path / "key"
    write_key_file(key_path)  # a new random key, mode 0600
    with Daemon([exe], key_file=str(key_path)) as d:
        base = ["status", "--host", LOCAL, "--tcp-port", str(d.tcp_port)]
        code, _, err = run_cli(capsys, *base)  # without a key: no id needed, none made
        assert code == 0 and not config.exists()
        code, _, err = run_cli(capsys, *base, "--key-file", str(tmp_path / "missing"))
        assert code == 4 and not config.exists()  # a failing key file: nothing made
        code, _, err = run_cli(capsys, *base, "--key-file", str(key_path))
        assert code == 0
        made = re.search(r"remote id is (\d+), made now and kept in (.+)$", err.strip())
        assert made is not None and made.group(2) == str(config), err
        rid = int(made.group(1))
        assert 0x100 <= rid <= 0xFFFFFFFF
        assert f"remote_id = {rid}" in config.read_text()
        code, _, err = run_cli(capsys, *base, "--key-file", str(key_path))
        assert (code, err) == (0, "")  # the same id, kept: nothing new to say
        assert config.read_text().count("remote_id") == 1


def test_remote_id_that_cannot_be_kept_is_one_line(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    # readable (absent) but not writable, even for root
    monkeypatch.setenv("ESTOP_CONFIG", "/proc/estop-test-config.toml")
    key_path = tmp_path / "key"
    write_key_file(key_path)  # a new random key, mode 0600
    code, _, err = run_cli(capsys, "status", "--host", LOCAL, "--key-file", str(key_path))
    line = error_line(err)
    assert code == 2 and "cannot keep this installation's remote id" in line
    assert "--remote-id" in line


@pytest.fixture
def keyed_unit(tmp_path: Path, estopd: str) -> Iterator[tuple[Daemon, bytes, str]]:
    exe = estopd
    key_path = tmp_path / "key"
    key = write_key_file(key_path)
    with Daemon([exe], key_file=str(key_path)) as d:
        yield d, key, str(key_path)


def test_a_remote_whose_counters_are_refused_as_replays_is_told_so(
        keyed_unit: tuple[Daemon, bytes, str], capsys: pytest.CaptureFixture[str]) -> None:
    """Another remote with the same id and the same key ran ahead (its counters are higher):
    the unit refuses this one's RELEASE as a replay, NAK 4, and the tool says what that means
    instead of a bare not_authenticated."""
    d, key, key_path = keyed_unit
    ahead = MessageCounter(start=(time_us() + 10**12))
    with StopChannel(LOCAL, d.tcp_port, identity=Identity(key, 42, ahead)) as other:
        other.status()
        other.release()  # authenticated (NAK no_live_link): the unit keeps its counter
    code, out, err = run_cli(capsys, "release", "--host", LOCAL, "--tcp-port", str(d.tcp_port),
                             "--key-file", key_path, "--remote-id", "42")
    assert code == 1 and out.strip().endswith("nak=not_authenticated")
    assert "refused remote id 42's counter as a replay" in err
    assert "give each remote its own --remote-id" in err and err.count("\n") == 1
    # its own id: no replay; the unit then answers for the link (no live link: NAK 2)
    code, out, err = run_cli(capsys, "release", "--host", LOCAL, "--tcp-port", str(d.tcp_port),
                             "--key-file", key_path, "--remote-id", "43")
    assert code == 1 and out.strip().endswith("nak=no_live_link") and err == ""


def time_us() -> int:
    import time

    return time.time_ns() // 1000


def test_without_a_key_a_nak_4_says_to_give_one(keyed_unit: tuple[Daemon, bytes, str],
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    d, _key, _path = keyed_unit
    code, out, err = run_cli(capsys, "release", "--host", LOCAL, "--tcp-port", str(d.tcp_port))
    assert code == 1 and "nak=not_authenticated" in out and "give --key-file" in err


def test_config_path_follows_xdg(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("XDG_CONFIG_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert config_path() == tmp_path / ".config" / "estop" / "config.toml"
    monkeypatch.setenv("XDG_CONFIG_HOME", "relative/ignored")  # XDG: relative paths are invalid
    assert config_path() == tmp_path / ".config" / "estop" / "config.toml"
    monkeypatch.setenv("ESTOP_CONFIG", str(tmp_path / "x.toml"))
    assert config_path() == tmp_path / "x.toml"
    assert os.environ["ESTOP_CONFIG"].endswith("x.toml")


def test_estopd_names_its_bus_as_python_can_does(estopd: str) -> None:
    """estopd's CAN interface is python-can's --channel; --can stays as its older name."""
    import subprocess

    exe = estopd
    for flag in ("--channel", "--can"):
        res = subprocess.run([exe, "--no-auth", flag, ""], capture_output=True, text=True,
                             timeout=10, check=False)
        assert res.returncode == 2
        assert res.stderr.strip() == ("estopd: error: invalid value '' for --channel "
                                      "(expected a network interface name)")
    usage = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=10,
                           check=True).stdout
    assert "[--channel IFACE]" in usage and "--can " not in usage


def test_a_command_may_take_an_optional_host(tmp_path: Path) -> None:
    """add_settings(host_required=False): the host stays None when nothing names one (the
    dashboard runs without a unit), and still comes from the environment when set."""
    import argparse

    from estop.commands.settings import add_settings

    p = argparse.ArgumentParser()
    add_settings(p, "host", "tcp_port", host_required=False)
    none = tmp_path / "none.toml"
    a = p.parse_args([])
    resolve_settings(a, {}, ConfigFile(none, COMMON_SETTINGS))
    assert a.host is None and a.tcp_port == tcp.DEFAULT_PORT
    a = p.parse_args([])
    resolve_settings(a, {"ESTOP_HOST": "10.1.2.3"}, ConfigFile(none, COMMON_SETTINGS))
    assert a.host == "10.1.2.3"


def test_first_uses_at_once_agree_on_one_remote_id(tmp_path: Path) -> None:
    """Several processes using a key for the first time at the same moment keep one id."""
    import subprocess
    import sys

    cfg = tmp_path / "cfg" / "config.toml"
    prog = ("import sys; from estop.commands.configfile import ConfigFile, installation_remote_id; "
            "from estop.commands.settings import COMMON_SETTINGS; from pathlib import Path; "
            "print(installation_remote_id(ConfigFile(Path(sys.argv[1]), COMMON_SETTINGS)))")
    procs = [subprocess.Popen([sys.executable, "-c", prog, str(cfg)], stdout=subprocess.PIPE,
                              text=True) for _ in range(6)]
    ids = {int(p.communicate(timeout=30)[0]) for p in procs}
    assert len(ids) == 1
    assert cfg.read_text().count("remote_id =") == 1
    assert f"remote_id = {ids.pop()}" in cfg.read_text()
