"""``estop demo``: version 3's story against a real estopd on loopback. The script
(:mod:`~estop.demo.story`), the operator's tablet (:mod:`~estop.demo.operator`), the attacker
(:mod:`~estop.demo.attacker`), the version-2 twin (:mod:`~estop.demo.twin`), what the bus says
and the car does (:mod:`~estop.demo.bus`, :mod:`~estop.demo.car`), the screen
(:mod:`~estop.demo.view`), the measurements (:mod:`~estop.demo.result`), the report
(:mod:`~estop.demo.report`) and the checks (:mod:`~estop.demo.checks`). The command line is
:mod:`estop.commands.demo`."""
