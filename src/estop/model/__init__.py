"""Pure models without I/O: the car (:mod:`~estop.model.vehicle`), its roll-out from recorded
frames (:mod:`~estop.model.rollout`), what a brake controller checks and commands
(:mod:`~estop.model.brakecheck`), the remote's Wi-Fi link (:mod:`~estop.model.wifi`)."""
