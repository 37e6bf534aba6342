"""The Cura plugin uses the core only through `kestimator.api`, and every name there works.

The plugin is a separate program that vendors the core (plugins/cura/build.py): it must not
reach into the core's modules or private names, or a change inside the core breaks it
unnoticed. `kestimator.api` is the one place those names are promised.
"""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest

from kestimator import api

from .conftest import PROJECT

PLUGIN_DIR = PROJECT / "plugins" / "cura" / "kestimator_cura"
CORE = "kestimator"
PUBLIC_API = "kestimator.api"


def _core_imports(path: Path) -> list[tuple[int, str, list[str]]]:
    """(line, module, names) of every import of the core in a plugin source."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == CORE:
                    found.append((node.lineno, alias.name, []))
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and \
                node.module.split(".")[0] == CORE:
            found.append((node.lineno, node.module, [alias.name for alias in node.names]))
    return found


def _plugin_sources() -> list[Path]:
    sources = sorted(PLUGIN_DIR.glob("*.py"))
    assert sources, "no plugin sources in %s" % PLUGIN_DIR
    return sources


def test_the_cura_plugin_imports_the_core_only_through_kestimator_api() -> None:
    offenders = []
    for path in _plugin_sources():
        for line, module, names in _core_imports(path):
            where = "%s:%d" % (path.relative_to(PROJECT), line)
            if module == PUBLIC_API:
                offenders += ["%s: %s is private" % (where, name) for name in names
                              if name.startswith("_") or name == "*"]
            elif module == CORE:
                # `import kestimator` or its package attributes (__version__), no submodule.
                offenders += ["%s: from kestimator import %s (use kestimator.api)" % (
                    where, name) for name in names if not name.startswith("__")]
            else:
                offenders.append("%s: imports %s (use kestimator.api)" % (where, module))
    assert not offenders


def test_every_name_the_plugin_imports_is_in_the_api() -> None:
    wanted = {name for path in _plugin_sources()
              for _, module, names in _core_imports(path) if module == PUBLIC_API
              for name in names}
    assert wanted and wanted <= set(api.__all__)


@pytest.mark.parametrize("name", api.__all__)
def test_every_api_name_resolves(name: str) -> None:
    value = getattr(api, name)
    if inspect.isfunction(value) or inspect.isclass(value):
        assert inspect.getdoc(value), name


def test_an_unknown_api_name_is_an_attribute_error() -> None:
    with pytest.raises(AttributeError):
        api.no_such_name  # noqa: B018
