"""Talking to a unit as a remote does: the TCP stop channel (:mod:`~estop.client.channel`), the
stop button and the stop and lift datagrams (:mod:`~estop.client.button`), the tablet's
control-packet sender (:mod:`~estop.client.sender`), key files (:mod:`~estop.client.keyfile`)
and one-shot requests (:mod:`~estop.client.oneshot`)."""
