"""`python -m bcf` is the same as the `bcf` console script."""

from bcf.cli import main

raise SystemExit(main())
