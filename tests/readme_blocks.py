"""Code blocks of README.md, found by the ``<!-- snippet: NAME -->`` marker on the line before them.

Tests execute the README's own text, so the snippets cannot drift from what is tested.
"""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_block(name: str) -> str:
    """The fenced code block right after ``<!-- snippet: name -->`` in README.md."""
    text = README.read_text()
    m = re.search(rf"<!-- snippet: {re.escape(name)} -->\n```[a-z]*\n(.*?)\n```", text, flags=re.S)
    if m is None:
        raise LookupError(f"README.md: no code block after '<!-- snippet: {name} -->'")
    return m.group(1)


def shrink(code: str, replacements: dict[str, str]) -> str:
    """``code`` with each budget replaced; every replaced text must occur exactly once."""
    for old, new in replacements.items():
        assert code.count(old) == 1, f"README snippet changed: {old!r} occurs {code.count(old)} times"
        code = code.replace(old, new)
    return code
