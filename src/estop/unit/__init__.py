"""estopd seen from outside: running it on loopback (:mod:`~estop.unit.daemon`), reading what it
writes (:mod:`~estop.unit.canlog`), talking to it over raw sockets (:mod:`~estop.unit.looplink`)."""
