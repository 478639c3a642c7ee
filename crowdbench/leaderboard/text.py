"""Text helpers: submission text escaped into the generated markdown (:func:`md`), values cut short for
one-line error messages (:func:`one_line`, :func:`short`), and row-level diffs of two generated files
(:func:`diff_rows`, for ``--check``). Pure functions, no crowdbench imports."""

from __future__ import annotations

import re
import reprlib
import unicodedata

# markdown that submission text must not produce in a table cell: a column (|), HTML (<, >), a link or an
# image ([, ]), code (`), emphasis (*, ~, and _ at a word boundary: intraword _ as in gatedgcn_td3_s0 is plain)
_MD_SPECIAL = re.compile(r"[\\|<>\[\]`*~]|(?<![A-Za-z0-9])_|_(?![A-Za-z0-9])")
# bidirectional overrides and isolates: they reorder the text around them
BIDI = frozenset("\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")
_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = 60
_REPR.maxlevel, _REPR.maxlist, _REPR.maxtuple, _REPR.maxdict = 2, 4, 4, 4


def bad_char(c: str) -> bool:
    """A character no one-line text may hold: control characters, line/paragraph separators, surrogates,
    private-use and unassigned code points, bidirectional controls."""
    return unicodedata.category(c) in ("Cc", "Cs", "Co", "Cn", "Zl", "Zp") or c in BIDI


def one_line(text) -> str:
    """``text`` on one line: runs of whitespace (newlines included) as one space, other control
    characters as ``?``."""
    return "".join("?" if bad_char(c) else c for c in " ".join(str(text).split()))


def md(text) -> str:
    """``text`` as the literal content of a markdown table cell (or list item): one line, with every
    character that would make a column, HTML, a link, code or emphasis backslash-escaped. A no-op on
    plain text (letters, digits, spaces, ``( ) , . - : / + = ;`` and intraword ``_``)."""
    return _MD_SPECIAL.sub(lambda m: "\\" + m.group(0), one_line(text))


def short(v, limit: int = 60) -> str:
    """``repr(v)`` for an error message: one line, nested containers elided, cut to ``limit`` characters
    + ``...`` (a value from a submission may be megabytes long)."""
    try:
        r = repr(v) if isinstance(v, str) and len(v) <= limit else _REPR.repr(v)
    except Exception:  # noqa: BLE001 - e.g. an int too large to print
        r = f"<{type(v).__name__}>"
    r = one_line(r)
    return r if len(r) <= limit else r[:limit] + "..."


def diff_rows(old: str, new: str) -> list[str]:
    """Rows that differ between two generated READMEs, named by section and first cell (the method, after
    a ranked table's ``#``)."""
    def rows(text):
        out, section = {}, ""
        for line in text.splitlines():
            if line.startswith("#"):
                section = line.lstrip("# ").strip()
            elif line.startswith("| ") and not line.startswith("|---"):
                cells = [c.strip() for c in line.split("|")]
                rank = cells[1] == "#" or cells[1].isdigit() or (cells[1] == "—" and len(cells) > 3)
                key = (section, cells[2] if rank else cells[1])  # a ranked table's row: named by its method
                while key in out:
                    key = (key[0], key[1] + "'")
                out[key] = line
            elif line.strip():
                out[(section, line.strip()[:60])] = line
        return out

    a, b = rows(old), rows(new)
    msgs = []
    for key in list(dict.fromkeys([*a, *b])):
        if a.get(key) != b.get(key):
            state = "missing in committed" if key not in a else "missing in fresh" if key not in b else "differs"
            msgs.append(f"[{key[0]}] row '{key[1]}': {state}" +
                        (f"\n    committed: {a[key]}\n    fresh:     {b[key]}" if state == "differs" else ""))
    return msgs
