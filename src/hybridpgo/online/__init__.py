"""The online mode's building blocks (see :mod:`.incremental`)."""
