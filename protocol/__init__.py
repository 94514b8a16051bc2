"""Everything of dinerf that crosses the network.

- :mod:`protocol.keys`        Zenoh key expressions (built and parsed in one place)
- :mod:`protocol.messages`    typed messages, model spec/signature, reject reasons
- :mod:`protocol.codec`       encode and decode messages (the wire format's entry point)
- :mod:`protocol.frame`       frame byte layout: magic, prefix, header fields, checksum
- :mod:`protocol.header`      header checks done before any large allocation
- :mod:`protocol.array_table` array payload layout: wire dtypes, table checks, packing
- :mod:`protocol.payload`     checksum, bounded decompression, message bodies
- :mod:`protocol.expectation` what a receiver accepts: swarm, model, peers, size caps
- :mod:`protocol.rounds`      per-round mailbox and barrier with deadline
- :mod:`protocol.membership`  topology, live neighbours, reference election, epochs
- :mod:`protocol.transport`   the Zenoh session (the only module importing zenoh)

Nothing here imports torch, and only ``protocol.transport`` imports zenoh, so the agent can use
the pure modules without either. This file imports no submodule on purpose.
"""
