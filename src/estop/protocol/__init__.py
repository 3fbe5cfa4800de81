"""Pure-Python codecs for every estop wire format (spec: shared/spec/PROTOCOL.md).

Written independently from the C core so the two can check each other:

- :mod:`estop.protocol.crc` -- CRC-8 SAE J1850 and CRC-32
- :mod:`estop.protocol.udp` -- UDP control packets (remote -> unit)
- :mod:`estop.protocol.tcp` -- TCP stop channel requests and replies
- :mod:`estop.protocol.can` -- ESTOP_BRAKE / ESTOP_STATUS CAN frames
- :mod:`estop.protocol.canlog` -- can-utils log lines
"""
