from uacell._entry import run

raise SystemExit(run())
