"""``estop dashboard``'s live status page: its inputs (:mod:`~estop.dashboard.feed`), what it
shows (:mod:`~estop.dashboard.model`, the link box :mod:`~estop.dashboard.linkbox`), the web
server (:mod:`~estop.dashboard.server`) and the page itself (``static/``). The command line is
:mod:`estop.commands.dashboard`."""
