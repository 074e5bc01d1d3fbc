"""`python -m bulbjax ...`: the `bulbjax` command without its installed entry point (e.g. on a
machine where the package is only on PYTHONPATH)."""

from bulbjax.cli import main

raise SystemExit(main())
