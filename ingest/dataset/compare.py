"""The first difference between two YAML-like trees, for errors that name what changed in a rerun."""

from __future__ import annotations

from typing import Any


def first_difference(old: Any, new: Any, path: str = "") -> str:
    """' (key.sub: old -> new)' for the first key whose values differ ('' when the trees are equal).

    Mappings are walked key by key (a key on one side only is 'absent' on
    the other); any other values are compared whole.
    """
    if isinstance(old, dict) and isinstance(new, dict):
        for key in [*old, *(k for k in new if k not in old)]:
            if key not in old or key not in new:
                was, now = old.get(key, "absent"), new.get(key, "absent")
                return f" ({path}{key}: {was} -> {now})"
            found = first_difference(old[key], new[key], f"{path}{key}.")
            if found:
                return found
        return ""
    if old == new:
        return ""
    if str(old) == str(new):  # '128' in a hand-edited file against the number 128: say which is which
        old, new = f"{old!r} ({type(old).__name__})", f"{new!r} ({type(new).__name__})"
    return f" ({path.rstrip('.') or 'value'}: {old} -> {new})"
