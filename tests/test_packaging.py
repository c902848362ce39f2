"""What a wheel ships: every file of the package that is not Python is listed in pyproject's
package-data (setuptools leaves out what is not, so an installed twinrl would miss the arm tasks'
MJCF or the renderer kernel's source, while an editable install works)."""

import fnmatch
import pathlib
import tomllib

import twinrl

ROOT = pathlib.Path(twinrl.__file__).parent


def test_every_data_file_of_the_package_is_package_data():
    pyproject = tomllib.loads((ROOT.parent / "pyproject.toml").read_text())
    data = pyproject["tool"]["setuptools"]["package-data"]
    missing = []
    for path in ROOT.rglob("*"):
        if not path.is_file() or path.suffix in (".py", ".pyc") or "__pycache__" in path.parts:
            continue
        package = ".".join(path.parent.relative_to(ROOT.parent).parts)
        if not any(fnmatch.fnmatch(path.name, pat) for pat in data.get(package, [])):
            missing.append(str(path.relative_to(ROOT.parent)))
    assert not missing, f"not in [tool.setuptools.package-data]: {missing}"
    assert "twinrl.envs.arm" in data and "twinrl.render.native" in data
