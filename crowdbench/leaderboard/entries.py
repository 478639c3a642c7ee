"""Row labels across submissions: who may share an ``entry`` (docs/submitting.md section 2).

A row of a track's table is every submission with one ``entry`` label, so a label is shared only by
seeds of one method: learned submissions trained on the same track with the same encoder, algorithm
and recipe (``experiment`` and the training overrides other than ``seed=``). A baseline's or the
oracle's label belongs to it alone. Labels are compared by a key that ignores case, Unicode
compatibility forms (NFKC) and the Cyrillic and Greek letters that look Latin, so a lookalike label
("Straight t\\u043e goal") is refused too, as are two names that differ only by case (they collide
on case-insensitive file systems).
"""

from __future__ import annotations

import unicodedata
from collections import Counter

from crowdbench.leaderboard.submission import Submission, SubmissionError
from crowdbench.leaderboard.text import short

# letters drawn like Latin ones (Unicode's confusables, the ones a keyboard layout offers)
LOOKALIKE = str.maketrans("АВЕКМНОРСТХЅІЈаеорсхуѕіјԁԛԝһӏΑΒΕΖΗΙΚΜΝΟΡΤΥΧαοριντυκ",
                          "ABEKMHOPCTXSIJaeopcxysijdqwhlABEZHIKMNOPTYXaopivtuk")


def label_key(label: str) -> str:
    """What two labels are compared by: NFKC, lookalike letters as Latin, case and spaces ignored."""
    text = unicodedata.normalize("NFKC", label).translate(LOOKALIKE)
    return " ".join(unicodedata.normalize("NFKC", text).casefold().split())


def recipe(sub: Submission) -> dict:
    """What seeds of one entry have in common."""
    d = sub.data
    if sub.kind != "learned":
        return {"kind": sub.kind}
    over = d.get("overrides") or []
    return {"kind": "learned", "encoder": d["encoder"], "algo": d["algo"], "net": d.get("net"),
            "experiment": d.get("experiment"),
            "overrides": sorted(o for o in over if not o.replace(" ", "").startswith("seed="))}


def model_of(d: dict) -> str:
    """What acts, for the tables' encoder column: a baseline's policy, a value entry's network (SARL's is
    no encoder of the registry; ``net: encoder`` is the encoder with a value head), else the encoder."""
    if d.get("net") not in (None, "encoder"):
        return d["net"]
    return d.get("encoder", d.get("policy", "—"))


def _describe(r: dict) -> str:
    return ", ".join(f"{k} {short(v, 40)}" for k, v in r.items() if v not in (None, []))


def entry_problems(subs: list[Submission]) -> dict[str, SubmissionError]:
    """``{name: rejection}`` of the submissions whose label (or name) may not be what they say."""
    out: dict[str, SubmissionError] = {}
    names: dict[str, str] = {}
    for s in sorted(subs, key=lambda s: s.name):
        other = names.setdefault(s.name.casefold(), s.name)
        if other != s.name:
            out[s.name] = SubmissionError(s.yaml_path, "name", f"{s.name!r} differs from submission {other!r} "
                                                                "only by case (they collide on macOS and Windows)")
    groups: dict[tuple[str, str], list[Submission]] = {}
    for s in subs:
        if s.name not in out:
            track = s.data.get("track", "v1") if s.kind == "learned" else ""
            groups.setdefault((label_key(s.entry), track), []).append(s)
    owners: dict[str, Submission] = {}  # label key -> a baseline / the oracle holding it
    for s in sorted(subs, key=lambda s: (s.kind == "learned", s.name)):
        if s.kind != "learned" and s.name not in out:
            owners.setdefault(label_key(s.entry), s)
    for (key, _), members in groups.items():
        owner = owners.get(key)
        counts = Counter(repr(recipe(s)) for s in members)
        # the recipe most members share, ties by name: one hostile submission cannot take a row over
        major = max(members, key=lambda s: (counts[repr(recipe(s))], [-ord(c) for c in s.name]))
        for s in members:
            if owner is not None and s is not owner:
                out[s.name] = SubmissionError(s.yaml_path, "entry", f"{short(s.entry)} is the row of {owner.kind} "
                                              f"{owner.name!r} ({short(owner.entry)}); a baseline's or the oracle's "
                                              "row takes no other submission: choose another entry")
            elif owner is None and s.entry != major.entry:
                out[s.name] = SubmissionError(s.yaml_path, "entry", f"{short(s.entry)} looks like {short(major.entry)}"
                                              f" of {major.name!r} (lookalike letters, case or invisible characters): "
                                              "use the same text or another entry")
            elif owner is None and recipe(s) != recipe(major):
                out[s.name] = SubmissionError(s.yaml_path, "entry", f"{short(s.entry)} is shared with {major.name!r} "
                                              f"({_describe(recipe(major))}) but this submission differs "
                                              f"({_describe(recipe(s))}): seeds of one method only")
    return out
