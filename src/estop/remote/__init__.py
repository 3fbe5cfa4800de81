"""The front-ends of ``estop remote``, each driving one :class:`estop.client.sender.Remote`: the
terminal's keys (:mod:`~estop.remote.keys`), a script (:mod:`~estop.remote.script`), a game
controller (:mod:`~estop.remote.gamepad`, its event mapping in
:mod:`~estop.remote.gamepadmap`)."""
