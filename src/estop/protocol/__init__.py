"""Pure-Python codecs for every estop wire format (spec: docs/PROTOCOL.md).

Written independently from the C code so the two can check each other:

- :mod:`estop.protocol.crc` -- CRC-8 SAE J1850 and CRC-32
- :mod:`estop.protocol.udp` -- plain UDP control packets (remote -> unit)
- :mod:`estop.protocol.tcp` -- plain TCP stop channel requests and replies, stream framing
- :mod:`estop.protocol.auth` -- authentication (section 5): the 60-byte control packet, the
  48-byte request and reply frames, tags, the key file's text
- :mod:`estop.protocol.can` -- ESTOP_BRAKE / ESTOP_STATUS CAN frames
- :mod:`estop.protocol.canlog` -- can-utils log lines
"""
