"""Deployment on a car (issue 17): `make install` puts the unit bound to the CAN interface,
the systemd-networkd file that brings that interface up at its bitrate and the configuration
naming it; systemd-analyze verifies the unit; the restart never spins; the key copy
docs/DEPLOY.md tells a team to make works as written.

systemd is not PID 1 here (nor in the harness VM), so what systemd does with the unit at run
time (BindsTo, the restart delay) is not exercised: docs/DEPLOY.md lists the checks to make
on the car."""

from __future__ import annotations

import os
import pwd
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from estop.client.keyfile import load_key_file
from repo import ROOT

UNIT = "usr/lib/systemd/system/estopd.service"
NETWORK = "etc/systemd/network/80-estop-can.network"

# The [Match], [Link] and [CAN] keys of systemd.network(5) in systemd 252 (Debian 12) that a
# CAN .network may use; the file must stay within them (networkd ignores unknown keys with
# only a log line, which nobody on a car reads).
NETWORK_KEYS = {
    "Match": {"Name", "MACAddress", "PermanentMACAddress", "Path", "Driver", "Type", "Kind"},
    "Link": {"RequiredForOnline", "ActivationPolicy", "MTUBytes"},
    "CAN": {"BitRate", "SamplePoint", "RestartSec", "Termination", "TripleSampling",
            "BusErrorReporting", "ListenOnly", "Loopback", "OneShot", "PresumeAck",
            "ClassicDataLengthCode", "DataBitRate", "DataSamplePoint", "FDMode", "FDNonISO"},
}


def _install(root: Path, *extra: str) -> None:
    subprocess.run(["make", "-s", "install", f"PREFIX={root}/usr", f"SYSCONFDIR={root}/etc",
                    *extra], cwd=ROOT, check=True, timeout=300, capture_output=True)


@pytest.fixture(scope="module")
def can1(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("install-can1")
    _install(root, "CAN_IFACE=can1", "CAN_BITRATE=250000")
    return root


def _sections(text: str) -> dict[str, dict[str, list[str]]]:
    out: dict[str, dict[str, list[str]]] = {}
    section = ""
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        m = re.fullmatch(r"\[(\w+)\]", line)
        if m:
            section = m[1]
            out.setdefault(section, {})
            continue
        key, _, value = line.partition("=")
        out[section].setdefault(key, []).append(value)
    return out


def test_unit_is_bound_to_the_can_interface_it_was_installed_for(can1: Path) -> None:
    unit = _sections((can1 / UNIT).read_text())
    dev = "sys-subsystem-net-devices-can1.device"
    assert unit["Unit"]["BindsTo"] == [dev]
    assert dev in unit["Unit"]["After"][0].split()
    assert dev in unit["Install"]["WantedBy"][0].split()  # started when can1 appears
    conf = (can1 / "etc/estop/estopd.conf").read_text()
    assert re.search(r"^ESTOPD_ARGS=.*--can can1\b", conf, re.M), conf


def test_unit_waits_for_its_interface_without_holding_the_boot(can1: Path) -> None:
    """Started by its interface only (issue 26): wanted by multi-user.target too, a boot
    without the interface held multi-user.target "starting" until the device's 90 s timeout
    (seen in the Debian 12 and 13 VMs of make systemd-vm)."""
    unit = _sections((can1 / UNIT).read_text())
    assert unit["Install"]["WantedBy"] == ["sys-subsystem-net-devices-can1.device"]


def test_unit_checks_the_set_up_before_each_start(can1: Path) -> None:
    """Set-ups that no restart mends end the start with estopd's own line, no restart loop
    (issue 26): as root the key file as installed, then as the service the options, the
    priority and the memory lock (`estopd --check`, tests/test_estopd_systemd.py)."""
    unit = _sections((can1 / UNIT).read_text())
    conds = unit["Service"]["ExecCondition"]
    exe = f"{can1}/usr/bin/estopd"
    assert conds == [f"+{exe} --check --key-file {can1}/etc/estop/key $ESTOPD_ARGS",
                     f"{exe} --check --mlock $ESTOPD_ARGS"], conds
    assert unit["Service"]["ExecStart"][0].startswith(f"{exe} --key-file ")


def test_restart_never_spins_and_never_gives_up(can1: Path) -> None:
    unit = _sections((can1 / UNIT).read_text())
    assert unit["Service"]["Restart"] == ["always"]
    delay = unit["Service"]["RestartSec"][0]
    assert re.fullmatch(r"\d+s", delay) and int(delay[:-1]) >= 1, delay
    assert unit["Unit"]["StartLimitIntervalSec"] == ["0"]


def test_systemd_analyze_verifies_the_bound_unit(can1: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze is missing (Debian package systemd, group check)"
    res = subprocess.run([analyze, "verify", str(can1 / UNIT)], capture_output=True,
                         text=True, timeout=60, check=False)
    assert res.returncode == 0 and res.stderr.strip() == "", res.stderr
    # systemd 252 knows no RestartSteps=: had the unit used it, verify would say so
    bad = can1 / "steps.service"
    bad.write_text((can1 / UNIT).read_text().replace("RestartSec=", "RestartSteps=5\nRestartSec="))
    res = subprocess.run([analyze, "verify", str(bad)], capture_output=True, text=True,
                         timeout=60, check=False)
    assert "Unknown key" in res.stderr and "RestartSteps" in res.stderr, res.stderr


def test_network_file_brings_the_interface_up_at_its_bitrate(can1: Path) -> None:
    path = can1 / NETWORK
    assert path.stat().st_mode & 0o777 == 0o644
    net = _sections(path.read_text())
    assert net["Match"]["Name"] == ["can1"]
    assert net["CAN"]["BitRate"] == ["250000"]
    assert net["Link"]["RequiredForOnline"] == ["no"]
    for section, keys in net.items():
        assert section in NETWORK_KEYS, section
        assert set(keys) <= NETWORK_KEYS[section], (section, set(keys) - NETWORK_KEYS[section])
    assert "@" not in path.read_text()


def test_install_keeps_a_teams_edited_network_file(can1: Path) -> None:
    path = can1 / NETWORK
    edited = path.read_text().replace("BitRate=250000", "BitRate=125000")
    path.write_text(edited)
    _install(can1)  # default CAN_IFACE=can0 now: the edited file and config stay
    assert path.read_text() == edited
    assert "--can can1" in (can1 / "etc/estop/estopd.conf").read_text()
    path.write_text(edited.replace("BitRate=125000", "BitRate=250000"))
    _install(can1, "CAN_IFACE=can1", "CAN_BITRATE=250000")


def test_team_key_copy_as_docs_deploy_says(can1: Path, tmp_path: Path) -> None:
    text = (ROOT / "docs/DEPLOY.md").read_text()
    line = next(s.strip() for s in text.splitlines() if "install -m 0600 -o" in s)
    assert line.startswith('sudo install -m 0600 -o "$USER" /etc/estop/key ~/estop.key'), line
    if os.geteuid() != 0:
        pytest.skip("the copy's owner can only be given by root")
    nobody = pwd.getpwnam("nobody")
    copy = tmp_path / "estop.key"
    subprocess.run(["install", "-m", "0600", "-o", "nobody", str(can1 / "etc/estop/key"),
                    str(copy)], check=True, timeout=10)
    st = copy.stat()
    assert st.st_uid == nobody.pw_uid and st.st_mode & 0o777 == 0o600
    assert load_key_file(copy) == load_key_file(can1 / "etc/estop/key")
