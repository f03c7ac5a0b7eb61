"""``python -m depthnerf`` (and ``torchrun -m depthnerf``) entry point."""

from depthnerf.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
