"""Scenarios: a named swarm experiment (dataset, split, topology, training, fault timeline) that
``dinerf-agent scenario run`` starts as real daemons, on loopback or in network namespaces, and
turns into a report. ``spec`` is the schema, ``netns`` the emulated network, ``runner`` the
orchestration, ``report`` the evaluation, ``compose`` the docker-compose export.
"""
