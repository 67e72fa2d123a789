"""`python -m admc.cli`: the admc-pipe command, for launchers that start modules (torchrun -m admc.cli train ...)."""

from admc.cli.app import main

if __name__ == "__main__":  # not when multiprocessing's spawn imports the parent's main module
    main()
