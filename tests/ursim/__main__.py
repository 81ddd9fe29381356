"""``python -m tests.ursim --port P --programs-dir D ...``: one simulated UR controller (server.py)."""

from .server import main

main()
