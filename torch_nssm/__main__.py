"""``python -m torch_nssm``: the command-line entry point (see :mod:`torch_nssm.cli`)."""

from .cli import main

if __name__ == "__main__":
    raise SystemExit(main())
