"""The analysis behind ``estop link`` (:mod:`estop.commands.link`): a recording of the control
link turned into false stops per hour per timeout.

Small modules with one-way dependencies: :mod:`estop.link.gaps` (gap cells) <-
:mod:`estop.link.histogram` (estopd's log) <- :mod:`estop.link.read` (the other input files,
the choice of reader); :mod:`estop.link.gaps` <- :mod:`estop.link.fit` (the stop rule and the
fit) <- :mod:`estop.link.unitcheck` (the unit's own counts against the model, with
:mod:`estop.link.poisson`) <- :mod:`estop.link.report` (rows, the recommended S and T) <-
:mod:`estop.link.format` (text, JSON) and :mod:`estop.link.plot`.

Inputs (one file; the kind is recognised from its first bytes, or named with ``--format``):

- ``log``: estopd's ``--log-json`` log. Its ``link_histogram`` events hold the gaps between
  consecutive valid control packets, binned in half-octaves (cumulative since the daemon
  started); each ``start`` event begins a new run and the runs are added up.
- ``times``: arrival times, one float (seconds) per line; blank lines and ``#`` comments skipped.
- ``pcap``: a capture (pcap or pcapng) of the control port: UDP datagrams to ``--port`` of a
  control packet's length (20, 16 or 60 bytes) are the packets.

The model is a two-state Gilbert channel at the known send rate: every packet the remote sends
is either received (good state) or lost (bad state); ``p_gb`` = P(good -> bad), ``p_bg`` =
P(bad -> good). A gap between two received packets of (k+1) send periods means k lost in a row.
Loss = p_gb / (p_gb + p_bg), mean burst = 1 / p_bg.

A stop comes at the deadline: with send period P and timeout D, after a packet at t0 the next
ones are due at t0 + P, t0 + 2P, ...; only those due strictly before t0 + D can keep the unit
alive, and there are n = ceil(D / P) - 1 of them. The unit stops when those n are all lost
(50 Hz, 200 ms: packets due at 20 .. 180 ms, n = 9; the 10th is due at the deadline itself,
when the stop has already come). False stops per hour = bursts of n or more losses per hour =
packets per hour x (1 - loss) x p_gb x (1 - p_bg)^(n - 1).
"""
