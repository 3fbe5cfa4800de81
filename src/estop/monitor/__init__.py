"""``estop monitor``'s watch of ESTOP_BRAKE / ESTOP_STATUS frames (:mod:`~estop.monitor.watch`)
and what it reads besides a live bus (:mod:`~estop.monitor.sources`). The command line is
:mod:`estop.commands.monitor`."""
