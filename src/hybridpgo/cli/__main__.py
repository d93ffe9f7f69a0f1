"""``python -m hybridpgo.cli``: the same as the ``hybridpgo`` console script."""

from . import main

raise SystemExit(main())
