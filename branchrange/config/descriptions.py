"""What each setting means, read from its settings class's docstring — the one place it is written.

The settings dataclasses (`branchrange.core.settings_check.Settings`) document their keys in three
ways, and `key_description` reads them in this order, the class first and then its bases:
a bullet (`- \\`key\\`: text`, or `- \\`a\\`, \\`b\\`: text` for keys that share it), an inline
definition in prose (`\\`key\\`: text` up to the end of its sentence or the next definition), and
last any sentence that names the key. The generated JSON Schema and the configuration reference
(`branchrange.config.schema`, `branchrange.config.reference`) take their descriptions
from here, so a key documented in its class is documented in the editor and the manual.
"""

from __future__ import annotations

import inspect
import re
from collections.abc import Iterator

from branchrange.core.settings_check import Settings

#: A bullet's head: one or more backticked keys, then a colon.
_BULLET = re.compile(r"^-\s+((?:`\w+`(?:,\s*|\s+and\s+|\s*/\s*)?)+):\s*(.*)$", re.DOTALL)
#: Where a sentence ends: a full stop and a space before a capital, a backtick or a quote.
_SENTENCE_END = re.compile(r"(?<=\.)\s+(?=[A-Z`'(])")


def _documented_classes(cls: type) -> Iterator[str]:
    """The docstrings of `cls` and its settings bases, nearest first (dataclass-made signatures skipped)."""
    for klass in cls.__mro__:
        if not (isinstance(klass, type) and issubclass(klass, Settings)) or klass is Settings:
            continue
        doc = klass.__dict__.get("__doc__") or ""
        if doc and not doc.startswith(f"{klass.__name__}("):
            yield inspect.cleandoc(doc)


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _bullets(doc: str) -> Iterator[tuple[list[str], str]]:
    """(keys, text) of every `- \\`key\\`: text` bullet of `doc`; a bullet runs to the next one or a blank line."""
    bullet: list[str] = []
    for line in [*doc.splitlines(), ""]:
        stripped = line.strip()
        if bullet and (not stripped or stripped.startswith("- ")):
            match = _BULLET.match(_one_line(" ".join(bullet)))
            if match:
                yield re.findall(r"`(\w+)`", match.group(1)), match.group(2)
            bullet = []
        if stripped.startswith("- "):
            bullet = [stripped]
        elif bullet and stripped:
            bullet.append(stripped)


def _inline_definition(doc: str, key: str) -> str:
    """The text after `\\`key\\`:` in prose, up to its sentence's end or the next `; \\`other\\`:`; '' when none."""
    match = re.search(rf"`{key}`:\s*(.+?)(?=;\s*`\w+`:|\.\s|\.$|$)", _one_line(doc))
    return match.group(1).strip() if match else ""


def _sentences_naming(doc: str, key: str) -> str:
    """The sentences of `doc` that name `\\`key\\``, joined; '' when none does."""
    sentences = _SENTENCE_END.split(_one_line(doc))
    return " ".join(s for s in sentences if f"`{key}`" in s)


def key_description(cls: type, key: str) -> str:
    """What `key` of settings class `cls` means, from the docstrings of `cls` and its bases ('' when none says)."""
    docs = list(_documented_classes(cls))
    for doc in docs:
        for keys, text in _bullets(doc):
            if key in keys:
                return text
    for find in (_inline_definition, _sentences_naming):
        for doc in docs:
            found = find(doc, key)
            if found:
                return found
    return ""


def class_summary(cls: type) -> str:
    """The first paragraph of the docstring of `cls` (or of its nearest documented settings base), on one line."""
    doc = next(_documented_classes(cls), "")
    return _one_line(doc.split("\n\n")[0])
