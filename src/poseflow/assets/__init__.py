"""Files shipped with the package."""

from pathlib import Path

__all__ = ["DEMO_CHECKPOINT"]

#: The ``small`` FunFlow6D checkpoint trained on generated scenes of the demo objects, with its
#: prepared objects in ``objects/`` (the README gives the command that trained it).
DEMO_CHECKPOINT = Path(__file__).resolve().parent / "demo_model"
