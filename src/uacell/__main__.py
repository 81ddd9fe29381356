from uacell.cli import main

raise SystemExit(main())
