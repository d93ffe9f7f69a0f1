"""``python -m hybridpgo``: the same as the ``hybridpgo`` console script."""

from .cli import main

raise SystemExit(main())
