"""``python -m poseflow.models --write-configs DIR``: each of :data:`RECIPES` as ``DIR/NAME.json``.

The checkout's ``configs/*.json`` are written so, and a test checks that they agree with
:data:`~poseflow.models.config.RECIPES`.
"""

from __future__ import annotations

import argparse

from poseflow.models.config import RECIPES, write_recipes


def main(argv: list[str] | None = None) -> None:
    """Parse the arguments and write the files."""
    parser = argparse.ArgumentParser(prog="python -m poseflow.models", description=__doc__)
    parser.add_argument(
        "--write-configs",
        required=True,
        metavar="DIR",
        help=f"write {', '.join(RECIPES)} as DIR/NAME.json",
    )
    for path in write_recipes(parser.parse_args(argv).write_configs):
        print(path)


if __name__ == "__main__":
    main()
