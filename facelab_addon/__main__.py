"""``python -m facelab_addon COMMAND ...``: FaceLab in batch (see facelab_addon/cli and docs/cli.md)."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
