"""Load a file under ``scripts/`` as a module, for the tests of those scripts
(import as ``from fixtures_scripts import load_script``)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

SCRIPTS = Path(__file__).resolve().parent.parent / "scripts"


def load_script(name: str) -> ModuleType:
    """``scripts/<name>.py`` executed as module ``name``, registered in ``sys.modules`` (dataclasses look their
    module up there); ``scripts/`` is on ``sys.path`` while it executes, so a script's imports of its siblings
    resolve."""
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    sys.path.insert(0, str(SCRIPTS))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(SCRIPTS))
    return module
