"""The live viewer's logic (``dinerf-agent view``), kept apart from the web server (cli/cmd_view.py).

- source.py: each robot's newest model and its panel line (the robots and their images: agent.runs);
- scene.py: cameras in the shared frame as frustums, the free camera as a render, the panel rows.
"""
