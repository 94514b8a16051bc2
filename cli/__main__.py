"""``python -m cli`` is ``dinerf-agent`` (handy where the console script is not on PATH)."""

from cli.main import main

main()
