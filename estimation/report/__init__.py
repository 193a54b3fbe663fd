"""Pose reporting to a mapping server over a serial port or BLE UART (issue 6).

* :mod:`.protocol`: framing (COBS, CRC-16/CCITT, zero delimiter) and the fault-proof deframer.
* :mod:`.messages`: message types and payload codecs.
* :mod:`.link_session`: the reliability state machine (the link session of a robot and the server), sans-IO.
* :mod:`.transport`: a pyserial port driven by one thread, with pacing and reconnection.
* :mod:`.mapframe`: the server's 2D map frame.
* :mod:`.reporter` / :mod:`.mapserver`: the two ends.
* :mod:`.relay`: a fault-injecting pseudo-terminal relay for tests and benchmarks.

Heavy modules are not imported here; import them from their submodules.
"""
