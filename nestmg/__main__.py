"""``python -m nestmg ...``: the ``nestmg`` command (:func:`nestmg.cli.main`)."""

from .cli import main

raise SystemExit(main())
