"""The checks of `make systemd-vm`, by name, in the order they run: the guest's checks record
under these names and the host's report fails any that never reported (a test that died half
way, a boot that hung)."""

INSTALL = "install as docs/DEPLOY.md says"
NETWORKD = "networkd brings vcan0 up from the installed files"
START = "systemctl start: running after READY=1, start line"
PROCESS = "the process: FIFO 50 loop, threads not, memory locked, no capability, dynamic user"
CREDENTIAL = "credential facts (where systemd puts the key)"
FRAMES = "frames on vcan0: STOPPED, reason boot (candump)"
RELEASE_STOP = "estop release and estop stop through the service (keyed)"
SECURITY = "systemd-analyze security estopd"
STEADY = "runs steadily (the watchdog is pinged)"
KILL9 = "kill -9: restarted after RestartSec, first frame a boot frame"
WATCHDOG = "kill -STOP: the watchdog kills and restarts it"
STOP = "systemctl stop: the last frame brakes"
BINDSTO = "BindsTo: stops with vcan0 gone, starts when it is back"
BAD_KEY_MISSING = "bad set-up: a missing key file"
BAD_KEY_MODE = "bad set-up: a key readable by others (0644 in a 0755 /etc/estop)"
BAD_KEY_ACL = "bad set-up: a key another user may read by its ACL (setfacl -m u:1000:r)"
BAD_IFACE = "bad set-up: a missing interface (--channel vcan9)"
BAD_RT_PRIO = "bad set-up: --rt-prio 60, above the service's 50"
JOURNAL = "journal: estopd's JSON lines, estop link --journal reads them"
PREPARE_NOCAN = "prepare a boot without vcan0"
NOCAN = "a boot without vcan0: the unit waits, no restart loop, starts when it appears"

PHASES = {
    "main": [INSTALL, NETWORKD, START, PROCESS, CREDENTIAL, FRAMES, RELEASE_STOP, SECURITY,
             STEADY, KILL9, WATCHDOG, STOP, BINDSTO, BAD_KEY_MISSING, BAD_KEY_MODE, BAD_KEY_ACL,
             BAD_IFACE, BAD_RT_PRIO, JOURNAL, PREPARE_NOCAN],
    "nocan": [NOCAN],
}
