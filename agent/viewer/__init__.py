"""The live viewer's logic (``dinerf-agent view``), kept apart from the web server (cli/cmd_view.py).

- source.py: which robots a run folder holds, where their images are, and their newest models;
- scene.py: cameras in the shared frame as frustums, the free camera as a render, the panel rows.
"""
