"""The package's data files: the robot model and the defaults that jobs read (gains, envelope).

They live in the repository's top-level ``assets/`` folder, which pyproject.toml installs as the
package data ``wbc_jax/assets`` of a wheel. A wheel's copy is used where it exists (``pip install .``);
otherwise the package runs from a checkout (``pip install -e .`` or ``PYTHONPATH``) and reads the
checkout's ``assets/`` beside it. Paths, not import-based resources: MuJoCo and the jobs need real files.
"""

from __future__ import annotations

import pathlib

_PACKAGE = pathlib.Path(__file__).resolve().parents[1]


def assets_dir() -> pathlib.Path:
    """The folder of the package data: ``wbc_jax/assets`` of an installed wheel, else the checkout's ``assets/``."""
    installed = _PACKAGE / "assets"
    return installed if installed.is_dir() else _PACKAGE.parent / "assets"


ASSETS = assets_dir()


def asset(relative: str) -> pathlib.Path:
    """The path of a package data file, e.g. ``asset("gains/com_critical_100.json")``."""
    return ASSETS / relative
