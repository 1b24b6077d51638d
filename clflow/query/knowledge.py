"""The material knowledge base (clflow/data/materials_kb.json) and its fuzzy text matcher.

The data file lists common objects and substances with a material type of the registry
(:mod:`clflow.materials`), a density and every parameter of that type, each number with a
plausible range and a source. Loading checks it against the registry, so the file can
never disagree with the simulator about names, units or valid intervals.

    >>> kb = load_knowledge_base()
    >>> best = kb.match(object_name="rubber duck")[0]
    >>> best.entry.name, best.entry.material, best.confidence
    ('rubber', 'elastic', 1.0)
"""

from __future__ import annotations

import difflib
import functools
import json
import math
import re
import unicodedata
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from clflow.errors import InputError
from clflow.materials import DENSITY, MATERIALS, Param, get_material

KB_FORMAT = "clflow-materials-kb"
KB_VERSION = 1

# How much a match is worth by where the text came from: the object name is what the user
# says the object is; a prompt describes a scene; a file name is often a camera default.
SOURCE_WEIGHTS = {"name": 1.0, "prompt": 0.9, "file": 0.7}
FUZZY_MIN_RATIO = 0.85  # difflib ratio for a misspelt word ("aluminum" ~ "aluminium": 0.94)
FUZZY_MIN_LENGTH = 5  # shorter words must match exactly ("cap" is not "can")
COMPOUND_MIN_LENGTH = 4  # alias glued to another word in a file name ("rubberduck")
COMPOUND_SCORE = 0.75
CONTAINER_FACTOR = 0.8  # "glass of water", "can of beans": the container is not the object
TYPE_NAME_CONFIDENCE = 0.3  # only a material type's name ("metal", "granular") matched
IDENTIFY_MIN_CONFIDENCE = 0.85  # a name matched at least this well is taken as that entry


@dataclass(frozen=True)
class Value:
    """One number of the knowledge base: the initial guess, its plausible range, its source."""

    value: float
    low: float
    high: float
    source: str


@dataclass(frozen=True)
class Entry:
    """An object or substance: its material type, density (kg/m^3) and parameters (SI)."""

    name: str
    material: str
    aliases: tuple[str, ...]
    density: Value
    parameters: dict[str, Value]
    note: str = ""

    def parameter_values(self) -> dict[str, float]:
        return {name: v.value for name, v in self.parameters.items()}


@dataclass(frozen=True)
class Match:
    """A knowledge-base entry found in the text.

    ``confidence`` in [0, 1] is the match strength (exact phrase 1, misspelt or glued words
    less) times the weight of where it was found (object name 1, prompt 0.9, file name
    0.7); it is not a probability. ``phrase`` is the alias that matched.
    """

    entry: Entry
    confidence: float
    phrase: str


@dataclass(frozen=True)
class KnowledgeBase:
    entries: tuple[Entry, ...]
    sources: dict[str, str]
    type_defaults: dict[str, str]  # material type -> entry name used when only the type is known
    fallback_material: str  # type used when nothing matches
    path: str

    def entry(self, name: str) -> Entry:
        for e in self.entries:
            if e.name == name:
                return e
        raise InputError(f"{self.path}: no knowledge-base entry named {name!r}")

    def default_entry(self, material: str) -> Entry:
        """The documented default entry of a material type (e.g. steel for metal)."""
        return self.entry(self.type_defaults[get_material(material).name])

    def match(self, object_name: str = "", prompt: str = "", file_name: str = "") -> list[Match]:
        """Entries named in the texts, best first (one match per entry, at most).

        Each alias of each entry is looked for as a phrase of whole words: exactly (after
        lower-casing, stripping accents and plurals), with misspelt words (difflib ratio
        >= 0.85 for words of 5+ letters), or glued into one word ("rubberduck", "sandcastle").
        A phrase followed by "of" is a container or a quantity ("glass of water") and
        counts 0.8 times. Ties go to the longer alias, then to the earlier position.
        """
        texts = [("name", object_name), ("prompt", prompt), ("file", file_name)]
        found = []  # (sort key, where, first word, end word, match)
        for where, text in texts:
            words = tokenize(text)
            for index, (score, start, end) in self._find_phrases(words).items():
                entry, alias, _ = self._phrases[index]
                if end < len(words) and words[end] == "of":
                    score *= CONTAINER_FACTOR
                confidence = round(score * SOURCE_WEIGHTS[where], 3)
                key = (confidence, len(alias), -start)
                found.append((key, where, start, end, Match(entry, confidence, alias)))
        # Greedy, best first: one match per entry, and a phrase inside a better one does
        # not count ("tin" in "tin foil", "can" in "soda can").
        found.sort(key=lambda f: f[0], reverse=True)
        taken: list[tuple[str, int, int]] = []
        matches: list[Match] = []
        for _, where, start, end, m in found:
            overlaps = any(w == where and start < e and s < end for w, s, e in taken)
            if not overlaps and all(m.entry is not other.entry for other in matches):
                taken.append((where, start, end))
                matches.append(m)
        return matches

    def identify(self, name: str) -> Entry | None:
        """The entry an object name clearly means ("steel spoon" -> steel), else None."""
        matches = self.match(object_name=name)
        return matches[0].entry if matches and matches[0].confidence >= IDENTIFY_MIN_CONFIDENCE else None

    @functools.cached_property
    def _phrases(self) -> list[tuple[Entry, str, tuple[str, ...]]]:
        """(entry, alias, alias words) of every alias."""
        return [(e, a, tuple(tokenize(a))) for e in self.entries for a in e.aliases]

    @functools.cached_property
    def _by_first_word(self) -> dict[str, list[int]]:
        index: dict[str, list[int]] = {}
        for i, (_, _, phrase) in enumerate(self._phrases):
            index.setdefault(phrase[0], []).append(i)
        return index

    @functools.cached_property
    def _by_glued(self) -> dict[str, list[int]]:
        """Aliases written as one word ("rubberduck") of 4+ letters -> phrase indices."""
        index: dict[str, list[int]] = {}
        for i, (_, _, phrase) in enumerate(self._phrases):
            if len(glued := "".join(phrase)) >= COMPOUND_MIN_LENGTH:
                index.setdefault(glued, []).append(i)
        return index

    @functools.cached_property
    def _vocabulary(self) -> dict[int, frozenset[str]]:
        """Alias words by length."""
        words = {w for _, _, phrase in self._phrases for w in phrase}
        return {n: frozenset(w for w in words if len(w) == n) for n in {len(w) for w in words}}

    def _find_phrases(self, words: list[str]) -> dict[int, tuple[float, int, int]]:
        """phrase index -> (score, first word, end word) of its best occurrence in ``words``:
        as whole words (score: mean word score), else glued into one word (1 if the word
        is the glued phrase, 0.75 if it starts or ends with it)."""
        similar = [self._similar_words(w) for w in words]
        best: dict[int, tuple[float, int, int]] = {}
        for i in range(len(words)):
            for first, first_score in similar[i].items():
                for index in self._by_first_word.get(first, ()):
                    phrase = self._phrases[index][2]
                    end = i + len(phrase)
                    if end > len(words):
                        continue
                    scores = [first_score] + [similar[i + k].get(a, 0.0) for k, a in enumerate(phrase) if k]
                    score = sum(scores) / len(scores)
                    if all(scores) and (index not in best or score > best[index][0]):
                        best[index] = (score, i, end)
        for i, w in enumerate(words):
            glued = [(1.0, w)] + [
                (COMPOUND_SCORE, part) for cut in range(COMPOUND_MIN_LENGTH, len(w)) for part in (w[:cut], w[-cut:])
            ]
            for score, part in glued:
                for index in self._by_glued.get(part, ()):
                    best.setdefault(index, (score, i, i + 1))
        return best

    @functools.cached_property
    def _similar_cache(self) -> dict[str, dict[str, float]]:
        return {}

    def _similar_words(self, word: str) -> dict[str, float]:
        """Alias words that ``word`` may stand for -> word score (1 exact, < 1 misspelt)."""
        cache = self._similar_cache
        if word not in cache:
            n = len(word)
            similar = {word: 1.0} if word in self._vocabulary.get(n, ()) else {}
            if n >= FUZZY_MIN_LENGTH:
                # ratio <= 2 min(n, m) / (n + m) >= r needs r n / (2 - r) <= m <= (2 - r) n / r
                r = FUZZY_MIN_RATIO
                lengths = range(max(FUZZY_MIN_LENGTH, math.ceil(r * n / (2 - r))), math.floor((2 - r) * n / r) + 1)
                for m in lengths:
                    similar.update((a, s) for a in self._vocabulary.get(m, ()) if (s := _word_score(a, word)))
            cache[word] = similar
        return cache[word]

    def match_type_name(self, *texts: str) -> str | None:
        """A registry material type or alias named in the texts ("metal", "granular"), or None."""
        for text in texts:
            words = tokenize(text)
            for n in (2, 1):  # "newtonian fluid" before "fluid"
                for i in range(len(words) - n + 1):
                    try:
                        return get_material("_".join(words[i : i + n])).name
                    except InputError:
                        continue
        return None


_WORD = re.compile(r"[a-z]+")
_CAMEL = re.compile(r"(?<=[a-z])(?=[A-Z])")


def _singular(word: str) -> str:
    if len(word) > 4 and word.endswith("ies"):
        return word[:-3] + "y"
    if word.endswith(("ches", "shes", "sses", "xes", "zes", "oes")):
        return word[:-2]
    if len(word) > 3 and word.endswith("s") and not word.endswith(("ss", "us", "is")):
        return word[:-1]
    return word


def tokenize(text: str) -> list[str]:
    """Lower-case singular words of ``text``: accents, digits and punctuation dropped and
    camelCase split ("IMG_0042-RubberDucks.jpg" -> ["img", "rubber", "duck", "jpg"])."""
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    text = _CAMEL.sub(" ", text).lower().replace("'", "")
    return [_singular(w) for w in _WORD.findall(text)]


def _word_score(alias_word: str, word: str) -> float:
    if alias_word == word:
        return 1.0
    short, total = min(len(alias_word), len(word)), len(alias_word) + len(word)
    if short < FUZZY_MIN_LENGTH or 2 * short < FUZZY_MIN_RATIO * total:  # ratio <= 2 short / total
        return 0.0
    matcher = difflib.SequenceMatcher(None, alias_word, word)
    if matcher.quick_ratio() < FUZZY_MIN_RATIO:  # an upper bound of ratio(), much cheaper
        return 0.0
    ratio = matcher.ratio()
    return ratio if ratio >= FUZZY_MIN_RATIO else 0.0


# --------------------------------------------------------------------------- loading


def _value(raw: object, param: Param, where: str, sources: dict[str, str]) -> Value:
    if not isinstance(raw, dict) or set(raw) != {"value", "range", "source"}:
        raise InputError(f"{where}: expected {{'value', 'range', 'source'}}, got {raw!r}")
    rng = raw["range"]
    if not (isinstance(rng, list) and len(rng) == 2):
        raise InputError(f"{where}.range: expected [low, high], got {rng!r}")
    value, low, high = (param.check(v, where) for v in (raw["value"], *rng))
    lo, hi = param.typical
    if not lo <= low <= value <= high <= hi:
        raise InputError(
            f"{where}: need {lo:g} <= low <= value <= high <= {hi:g} {param.unit} "
            f"(the registry's typical range), got value {value:g} in [{low:g}, {high:g}]"
        )
    if raw["source"] not in sources:
        raise InputError(f"{where}.source: {raw['source']!r} is not a key of 'sources'")
    return Value(value, low, high, raw["source"])


def _entry(raw: dict, where: str, sources: dict[str, str]) -> Entry:
    keys = {"name", "material", "aliases", "density", "parameters"}
    if not isinstance(raw, dict) or not keys <= set(raw) or not set(raw) <= keys | {"note"}:
        raise InputError(f"{where}: an entry needs exactly the keys {sorted(keys)} (and 'note')")
    where = f"{where} ({raw['name']})"
    mat = get_material(raw["material"])
    if raw["material"] != mat.name:
        raise InputError(f"{where}.material: write the registry name {mat.name!r}, not {raw['material']!r}")
    params = raw["parameters"]
    if not isinstance(params, dict) or set(params) != set(mat.param_names):
        raise InputError(f"{where}.parameters: {mat.name} needs exactly {list(mat.param_names)}, got {sorted(params)}")
    aliases = raw["aliases"]
    if not aliases or not all(isinstance(a, str) and tokenize(a) for a in aliases):
        raise InputError(f"{where}.aliases: expected a non-empty list of words, got {aliases!r}")
    return Entry(
        name=raw["name"],
        material=mat.name,
        aliases=tuple(aliases),
        density=_value(raw["density"], DENSITY, f"{where}.density", sources),
        parameters={n: _value(params[n], mat.param(n), f"{where}.parameters.{n}", sources) for n in mat.param_names},
        note=raw.get("note", ""),
    )


def load_knowledge_base(path: str | Path | None = None) -> KnowledgeBase:
    """Read and check a knowledge-base file (default: the one shipped with clflow).

    Every value and range must lie in the registry's typical range for its parameter,
    every source must be listed, every alias must belong to one entry only and every
    material type must have a default entry; anything else is an :class:`InputError`.
    """
    if path is None:
        return _shipped_knowledge_base()
    from clflow.fileio import read_json

    return _parse(read_json(path, "knowledge base"), str(path))


@functools.cache
def _shipped_knowledge_base() -> KnowledgeBase:
    ref = resources.files("clflow") / "data" / "materials_kb.json"
    return _parse(json.loads(ref.read_text()), str(ref))


def _parse(raw: object, where: str) -> KnowledgeBase:
    if not isinstance(raw, dict) or raw.get("format") != KB_FORMAT or raw.get("version") != KB_VERSION:
        raise InputError(f"{where}: not a {KB_FORMAT} file of version {KB_VERSION}")
    sources = raw.get("sources", {})
    entries = tuple(_entry(e, f"{where}: entries[{i}]", sources) for i, e in enumerate(raw.get("entries", [])))
    owner: dict[tuple[str, ...], str] = {}
    for e in entries:
        for alias in (e.name, *e.aliases):
            key = tuple(tokenize(alias))
            if owner.setdefault(key, e.name) != e.name:
                raise InputError(f"{where}: alias {alias!r} of {e.name!r} already belongs to {owner[key]!r}")
    kb = KnowledgeBase(entries, sources, raw.get("type_defaults", {}), raw.get("fallback_material", ""), where)
    if set(kb.type_defaults) != set(MATERIALS):
        raise InputError(f"{where}: type_defaults must name one entry for each of {list(MATERIALS)}")
    for material, name in kb.type_defaults.items():
        if kb.entry(name).material != material:
            raise InputError(f"{where}: type_defaults[{material!r}] = {name!r} is not a {material} entry")
    if kb.fallback_material not in MATERIALS:
        raise InputError(f"{where}: fallback_material {kb.fallback_material!r} is not a material type")
    return kb
