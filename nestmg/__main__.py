"""``python -m nestmg ...``: the ``nestmg`` command (:func:`nestmg.cli.main`)."""

if __name__ == "__main__":  # not when a tool imports every module of the package
    from .cli import main

    raise SystemExit(main())
