"""Ingest: the UDP daemon (``cranetwin.ingest.daemon``) and the machine-side sender
(``cranetwin.ingest.sender``). Sockets and timers live here; the wire format and the protocol
state machines are the sans-IO :mod:`cranetwin.protocol`.
"""
