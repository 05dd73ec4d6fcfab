"""A Griffe extension for the API reference: the Sphinx roles flightsim's docstrings use
(``:func:`check_settings```, ``:class:`~flightsim.core.settings.Settings```) become cross-references.

Each role becomes an optional cross-reference to the object's full path (resolved in the scope of the
docstring's object): a link when that object is documented on some page, plain code otherwise, and never a
warning. Loaded by mkdocstrings through ``extensions`` in ``mkdocs.yml``.
"""
from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|attr|data|exc|obj|const):`(~?)([\w.]+)(\(\))?`")
PACKAGES = ("flightsim", "kernels", "trajectories")


def _full_path(obj: griffe.Object, target: str) -> str:
    """``target`` as a full dotted path: as written when it names a package of the project, else resolved from the
    scope of ``obj`` (its first name through the module's imports and members), else as written."""
    if target.split(".")[0] in PACKAGES:
        return target
    first, _, rest = target.partition(".")
    scope = obj if obj.is_module or obj.is_class else obj.parent
    while scope is not None:
        try:
            found = scope.resolve(first)
        except (griffe.NameResolutionError, AttributeError, KeyError):
            scope = scope.parent
            continue
        return f"{found}.{rest}" if rest else found
    return target


def _rewrite(obj: griffe.Object, text: str) -> str:
    def link(match: re.Match) -> str:
        tilde, target, call = match.group(1), match.group(2), match.group(3) or ""
        shown = (target.rsplit(".", 1)[-1] if tilde else target) + call
        return f'<autoref identifier="{_full_path(obj, target)}" optional>`{shown}`</autoref>'

    return ROLE.sub(link, text)


def _walk(obj: griffe.Object) -> None:
    if obj.is_alias:
        return
    if obj.docstring is not None and ":" in obj.docstring.value and "`" in obj.docstring.value:
        obj.docstring.value = _rewrite(obj, obj.docstring.value)
    for member in obj.members.values():
        _walk(member)


class SphinxRoles(griffe.Extension):
    """Turn ``:role:`target``` in docstrings into optional cross-references (see the module's docstring), once a
    package is loaded (``on_package`` in recent Griffe, ``on_package_loaded`` in older releases; where both run, the
    second finds no role left)."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        _walk(pkg)

    def on_package_loaded(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        _walk(pkg)
