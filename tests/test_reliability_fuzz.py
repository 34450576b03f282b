"""Config fuzzing (issue 10, part 1): hostile YAML and config dicts.

Every generated input is either accepted as a valid config (then it is a sane
:class:`~pipeline.config.Config` that survives a YAML round trip) or refused with a
:class:`~pipeline.errors.ConfigError` whose one-line message names the key (or, for
text that is not YAML at all, the file and the line). Any other exception fails the
test, and no YAML tag may construct a Python object (a sentinel file is never created).

The default suite runs a quick subset (``QUICK`` examples per property); the tests
marked ``reliability`` run ``FULL`` examples each (``make test-reliability``).
Counts of the cases tried go to ``$RELIABILITY_COUNTS`` (a JSON file) when that is set.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import ROOT
from pipeline._util.validate import key_text as _key_text
from pipeline.config import (TOP_KEYS, Config, apply_overrides, config_from_dict,
                             config_to_yaml, load_config)
from pipeline.errors import ConfigError

QUICK, FULL = 60, 2500

BASE_TEXT = (ROOT / "configs/cantilever.yaml").read_text().replace(
    "size: 0.005", "size: 0.02")
BASE = yaml.safe_load(BASE_TEXT.replace("69.0e9", "69.0e+9"))
assert config_from_dict(BASE).mesh.size == 0.02

# Which top-level keys an error may name after a change under a given top-level key:
# the key itself, or one validated against it (mesh.size against the box, reduction
# against the ports, region names used by supports and ports, ...).
RELATED = {
    "geometry": {"geometry", "mesh", "lumped", "supports", "ports", "connections", "regions"},
    "modes": {"modes", "reduction"},
    "ports": {"ports", "reduction"},
    "regions": {"regions", "supports", "ports", "connections"},
    "reduction": {"reduction", "damping"},
    "damping": {"damping"},
    "supports": {"supports", "reduction"},  # no supports: no static correction
}

COUNTS: Counter = Counter()


@pytest.fixture(scope="module", autouse=True)
def _report_counts():
    yield
    from conftest import add_reliability_counts

    add_reliability_counts("fuzz", COUNTS)


def _settings(n: int):
    return settings(max_examples=n, deadline=None, derandomize=False,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.filter_too_much])


# --------------------------------------------------------------------------- strategies
def _nest(depth: int, kind: str):
    value: object = "x"
    for _ in range(depth):
        value = [value] if kind == "list" else {"k": value}
    return value


def _laughs(levels: int):
    """Shared sub-lists whose full expansion is 10**levels items (a billion laughs)."""
    value: object = ["lol"] * 10
    for _ in range(levels):
        value = [value] * 10
    return value


HOSTILE_STRINGS = ["", " ", "\n", "a\nb", "abc\n", "\t", "名前", "ñandú", "🚀", "\x00", "a\x00b",
                   "../../etc/passwd", "/dev/zero", "a" * 65, "a" * 5000, "all", "root", "tip",
                   "x", "y", "z", "none", "null", "~", "yes", "no", "on", "1e5", "0x10", ".nan",
                   "${HOME}", "$(rm -rf /)", "'; drop table", "\u202e", "\ufeff", "Cantilever",
                   "force", "displacement", "box", "step", "plane", "rigid", "uniform"]
HUGE_INTS = [2**63, -(2**63) - 1, 10**400, -(10**400)]
# ints beyond Python's 4300-digit str() limit (built, since hypothesis reprs sampled values)
beyond_str_limit = st.builds(lambda sign: sign * 10**5000, st.sampled_from([1, -1]))
SPECIAL_FLOATS = [0.0, -0.0, 5e-324, -5e-324, 1e-300, 1e-12, 1e308, -1e308, math.inf, -math.inf,
                  math.nan, 0.5, 0.49999999999, -0.99999999, 1e13, 1e13 * (1 + 1e-15)]

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-10, 1000), st.integers(),
    st.sampled_from(HUGE_INTS), beyond_str_limit, st.floats(), st.sampled_from(SPECIAL_FLOATS),
    st.floats(1e-4, 1.0), st.text(max_size=12), st.sampled_from(HOSTILE_STRINGS),
    st.binary(max_size=8), st.dates(), st.datetimes(),
    st.sampled_from([(1.0, 2.0, 3.0), frozenset({"x"}), {"x", "y"}, 1j, b"\xff", object]),
)
containers = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),
        st.dictionaries(st.one_of(st.sampled_from(sorted(TOP_KEYS) + ["kind", "size", "E", "nu",
                                                                     "rho", "region", "fix"]),
                                  st.text(max_size=6), st.integers(), st.none(), st.booleans()),
                        inner, max_size=4),
    ),
    max_leaves=8,
)
values = st.one_of(
    scalars, containers,
    st.builds(_nest, st.integers(1, 3000), st.sampled_from(["list", "dict"])),
    st.builds(_laughs, st.integers(5, 30)),
    st.lists(st.floats(), min_size=3, max_size=3),  # vectors, valid and not
    st.lists(st.sampled_from(HUGE_INTS + SPECIAL_FLOATS + [1, 0, -1]), min_size=3, max_size=3),
)


def _paths(node, prefix=()):
    """Every key path of a nested dict/list (sections, items and leaves)."""
    out = []
    if isinstance(node, dict):
        for key, value in node.items():
            out.append(prefix + (key,))
            out += _paths(value, prefix + (key,))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            out.append(prefix + (i,))
            out += _paths(value, prefix + (i,))
    return out


OPTIONAL_PATHS = [
    ("regions",), ("regions", "r"), ("regions", "r", "kind"), ("regions", "r", "point"),
    ("regions", "r", "normal"), ("regions", "r", "lower"), ("regions", "r", "radius"),
    ("connections",), ("connections", 0), ("craig_bampton",), ("craig_bampton", "modes"),
    ("modes", "solver"), ("modes", "tolerance"), ("mesh", "algorithm"), ("geometry", "path"),
    ("geometry", "scale"), ("damping", "ratios"), ("damping", "alpha"), ("damping", "beta"),
    ("supports", 0, "fix"), ("supports", 1), ("ports", "inputs", 1), ("ports", "outputs", 0, "x"),
]
PATHS = sorted(_paths(BASE), key=repr) + OPTIONAL_PATHS
paths = st.one_of(
    st.sampled_from(PATHS),
    st.tuples(st.text(min_size=1, max_size=8)),  # an unknown top-level key
    st.builds(lambda p, k: p[:-1] + (k,), st.sampled_from(PATHS), st.text(max_size=8)),
)


@st.composite
def mutated_configs(draw):
    """BASE with 1-3 changes (set a hostile value, or delete a key); returns (raw, tops)."""
    raw = copy.deepcopy(BASE)
    tops = set()
    for _ in range(draw(st.integers(1, 3))):
        path = draw(paths)
        tops.add(str(path[0]))
        if draw(st.integers(0, 4)) == 0:
            _delete(raw, path)
        else:
            _set(raw, path, draw(values))
    return raw, tops


def _set(raw, path, value):
    node = raw
    for key, nxt in zip(path[:-1], path[1:]):
        if isinstance(node, list):
            if not (isinstance(key, int) and key < len(node)):
                node.append({} if not isinstance(nxt, int) else [])
                key = len(node) - 1
        elif isinstance(node, dict):
            if key not in node or not isinstance(node[key], (dict, list)):
                node[key] = [] if isinstance(nxt, int) else {}
        else:
            return
        node = node[key]
    last = path[-1]
    if isinstance(node, list):
        if isinstance(last, int) and last < len(node):
            node[last] = value
        else:
            node.append(value)
    elif isinstance(node, dict):
        node[last] = value


def _delete(raw, path):
    node = raw
    for key in path[:-1]:
        try:
            node = node[key]
        except (KeyError, IndexError, TypeError):
            return
    try:
        del node[path[-1]]
    except (KeyError, IndexError, TypeError):
        pass


# --------------------------------------------------------------------------- checks
KEY_RE = re.compile(r"config key '([^']*)'")


def _walk_numbers(obj):
    if dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            yield from _walk_numbers(getattr(obj, f.name))
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from _walk_numbers(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            yield from _walk_numbers(v)
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield obj


def check_accepted(cfg: Config) -> None:
    """An accepted config is sane and survives the YAML round trip unchanged."""
    assert isinstance(cfg, Config)
    assert re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}", cfg.name), cfg.name
    assert all(math.isfinite(v) for v in _walk_numbers(cfg))
    assert type(cfg.mesh.order) is int and cfg.mesh.order in (1, 2)
    assert type(cfg.modes.count) is int and 1 <= cfg.modes.count <= 500
    assert cfg.material.E > 0 and -1 < cfg.material.nu < 0.5 and cfg.material.rho > 0
    assert cfg.mesh.size > 0
    for port in cfg.ports.inputs + cfg.ports.outputs:
        assert math.isfinite(math.fsum(v * v for v in port.direction)) and any(port.direction)
    for s in cfg.supports:
        assert s.fix and set(s.fix) <= {"x", "y", "z"}
    again = config_from_dict(yaml.safe_load(config_to_yaml(cfg)), source=cfg.source)
    assert again == cfg


def check_refused(exc: ConfigError, tops: set[str] | None) -> None:
    """One line, bounded, naming a key (of the right section when we know which)."""
    msg = str(exc)
    assert "\n" not in msg and len(msg) < 700, msg
    if "not valid YAML" in msg or "is empty" in msg:
        assert tops is None, msg  # only text input can fail to parse
        return
    m = KEY_RE.search(msg)
    assert m, f"no key named in: {msg}"
    key = m.group(1)
    if tops is not None:
        allowed = {"<root>"} | set().union(*(RELATED.get(t, {t}) for t in tops))
        allowed |= {_key_text(t) for t in tops}
        assert any(key == t or key.startswith((t + ".", t + "[")) for t in allowed), (msg, tops)


def verdict_of_dict(raw, tops):
    try:
        cfg = config_from_dict(raw)
    except ConfigError as exc:
        check_refused(exc, tops)
        COUNTS["dict_refused"] += 1
        return "refused"
    check_accepted(cfg)
    COUNTS["dict_accepted"] += 1
    return "accepted"


# --------------------------------------------------------------------------- dict fuzzing
def _dict_fuzz(case):
    raw, tops = case
    verdict_of_dict(raw, tops)


@_settings(QUICK)
@given(mutated_configs())
def test_hostile_config_dicts_quick(case):
    _dict_fuzz(case)


@pytest.mark.reliability
@_settings(FULL)
@given(mutated_configs())
def test_hostile_config_dicts_full(case):
    _dict_fuzz(case)


@_settings(QUICK)
@given(st.one_of(values, st.dictionaries(st.text(max_size=10), values, max_size=5)))
def test_arbitrary_top_level_values(raw):
    verdict_of_dict(raw, None)


def test_valid_variants_are_accepted():
    """The mutation machinery does reach valid configs (not only refusals)."""
    raw = copy.deepcopy(BASE)
    for path, value in [(("mesh", "size"), 0.03), (("modes", "count"), 12),
                        (("material", "nu"), -0.5), (("name", ), "a.b-c_9"),
                        (("damping", "kind"), "none"), (("modes", "tolerance"), 1e-10)]:
        _set(raw, path, value)
    assert verdict_of_dict(raw, None) == "accepted"


# --------------------------------------------------------------------------- YAML text fuzzing
SENTINEL_NAME = "PWNED_SENTINEL"
TAG_FRAGMENTS = [
    "!!python/object/apply:builtins.open ['{s}', 'w']",
    "!!python/object/apply:os.mkdir ['{s}']",
    "!!python/object/apply:os.system ['touch {s}']",
    "!!python/object/new:pathlib.Path ['{s}']",
    "!!python/object:builtins.object {{}}",
    "!!python/name:os.system",
    "!!python/module:os",
    "!!python/tuple [1, 2, 3]",
    "!<tag:yaml.org,2002:python/object/apply:os.mkdir> ['{s}']",
    "!!binary aGVsbG8=", "!!binary '###'", "!!set {{a, b}}", "!!omap [a: 1, b: 2]",
    "!!pairs [a: 1]", "!!timestamp 2001-12-14", "!!float nan", "!!float '1e400'", "!!int 0x1F",
    "!!int '9{big}'", "!!str 1", "!!null ''", "!!bool yes", "!custom x", "!foo {{a: 1}}",
    "!!map [1, 2]", "!!seq {{a: 1}}",
]
VALUE_FRAGMENTS = [
    ".nan", ".inf", "-.inf", "1e400", "-1e400", "1e-400", "69.0e9", "6.9e+10", "0o17", "0x_1",
    "1_000", "1:30", "2020-02-30", "2020-01-01 25:61:00", "~", "null", "yes", "No", "off", "'",
    '"', "{{", "[", "]", "}}", "&a [*a]", "&b {{x: *b}}", "*undefined", "'\\x00'", '"\\ud800"',
    '"\\x00"', '"名前"', "🚀", "? [a]\n  : b", "{{<<: {{kind: box}}}}", "[1, 2, 3]", "[0, 0, 0]",
    "[1e308, 1e308, 1e308]", "9" * 5000, "[" * 400 + "]" * 400, "[" * 3000, "{{a: " * 300,
    "|\n  text\n  lines", ">-\n  folded", "- a\n- b", "---\nname: x\n---\n", "%YAML 1.2\n---",
    "%TAG ! tag:yaml.org,2002:python/object/apply:\n---\n!os.system ['touch {s}']",
]
TAG_FRAGMENTS = [f.format(s=SENTINEL_NAME, big="9" * 5000) for f in TAG_FRAGMENTS]
VALUE_FRAGMENTS = [f.format(s=SENTINEL_NAME) for f in VALUE_FRAGMENTS]
text_fragments = st.one_of(st.sampled_from(TAG_FRAGMENTS + VALUE_FRAGMENTS),
                           st.text(max_size=20),
                           st.integers().map(str), st.floats().map(repr))
# where a fragment goes in the base file: after "key:" of a line, or replacing a line
BASE_LINES = BASE_TEXT.splitlines()


@st.composite
def yaml_texts(draw):
    lines = list(BASE_LINES)
    for _ in range(draw(st.integers(1, 3))):
        frag = draw(text_fragments)
        i = draw(st.integers(0, len(lines) - 1))
        how = draw(st.integers(0, 3))
        line = lines[i]
        if how == 0 and ":" in line and not line.lstrip().startswith("#"):
            key = line.split(":", 1)[0]
            lines[i] = f"{key}: {frag}"
        elif how == 1:
            lines[i] = frag
        elif how == 2:
            lines.insert(i, f"{draw(st.sampled_from(list(TOP_KEYS) + ['x', 'E']))}: {frag}")
        else:  # inside a flow mapping: mesh: {order: 2, size: FRAG}
            lines[i] = re.sub(r"(:\s*)([^,{}\[\]#]+)(?=[,}])", lambda m: m.group(1) + frag, line,
                              count=1)
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def yaml_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz_yaml")


def _yaml_fuzz(text: str, where: Path, overrides=()):
    path = where / "c.yaml"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    cwd = os.getcwd()
    os.chdir(where)  # a relative sentinel path would be created here
    try:
        cfg = load_config(path, overrides)
    except ConfigError as exc:
        msg = str(exc)
        assert "\n" not in msg and len(msg) < 900, msg
        assert str(path) in msg or "override" in msg, msg
        assert KEY_RE.search(msg) or "not valid YAML" in msg or "is empty" in msg \
            or "at the top level" in msg or "override" in msg \
            or "cannot be read" in msg, msg
        COUNTS["yaml_refused"] += 1
    else:
        check_accepted(cfg)
        COUNTS["yaml_accepted"] += 1
    finally:
        os.chdir(cwd)
    for p in (where / SENTINEL_NAME, Path(cwd) / SENTINEL_NAME):
        assert not p.exists(), "a YAML tag constructed an object"


@_settings(QUICK)
@given(yaml_texts())
def test_hostile_yaml_text_quick(yaml_dir, text):
    _yaml_fuzz(text, yaml_dir)


@pytest.mark.reliability
@_settings(FULL)
@given(yaml_texts())
def test_hostile_yaml_text_full(yaml_dir, text):
    _yaml_fuzz(text, yaml_dir)


@_settings(QUICK)
@given(st.text(max_size=200))
def test_random_text_is_refused_or_valid(yaml_dir, text):
    _yaml_fuzz(text, yaml_dir)


@pytest.mark.parametrize("fragment", TAG_FRAGMENTS)
def test_every_tag_fragment_is_refused_or_plain_data(yaml_dir, fragment):
    """Each tag once, in every position of the name and of a number (deterministic)."""
    frag = fragment
    for text in (BASE_TEXT.replace("name: cantilever", f"name: {frag}"),
                 BASE_TEXT.replace("rho: 2700.0}", f"rho: {frag}}}"),
                 BASE_TEXT + f"extra: {frag}\n"):
        _yaml_fuzz(text, yaml_dir)


# --------------------------------------------------------------------------- overrides
override_keys = st.one_of(
    st.sampled_from([".".join(map(str, p)) for p in PATHS]),
    st.sampled_from(["supports[0].fix", "supports[9].region", "ports.inputs[0].direction[1]",
                     "mesh..size", "[0]", ".", "a b", "mesh.size.x", "name.x", "regions.r.kind"]),
    st.text(max_size=12),
)
override_values = st.one_of(text_fragments, st.sampled_from(["0.03", "12", "true", "[y]", ""]))


@st.composite
def override_lists(draw):
    out = []
    for _ in range(draw(st.integers(1, 3))):
        if draw(st.integers(0, 9)) == 0:
            out.append(draw(st.text(max_size=30)))  # no '=' at all, or junk
        else:
            out.append(f"{draw(override_keys)}={draw(override_values)}")
    return out


@_settings(QUICK)
@given(override_lists())
def test_hostile_overrides_quick(yaml_dir, overrides):
    _yaml_fuzz(BASE_TEXT, yaml_dir, overrides)


@pytest.mark.reliability
@_settings(FULL)
@given(override_lists())
def test_hostile_overrides_full(yaml_dir, overrides):
    _yaml_fuzz(BASE_TEXT, yaml_dir, overrides)


def test_overrides_never_change_the_callers_dict():
    raw = copy.deepcopy(BASE)
    apply_overrides(raw, ["mesh.size=0.5", "supports[0].fix=[x]", "new.key=1"])
    assert raw == BASE


# --------------------------------------------------------------------------- regressions
REGRESSIONS = [
    # each of these raised a non-ConfigError (or was accepted) before issue 10
    (("name",), "abc\n", r"'name': got 'abc\\n'"),
    (("material", "E"), 10**400, r"'material.E': got <an integer of about 401 digits>, expected "
                                 r"a finite number"),
    (("modes", "count"), 10**5000, r"'modes.count': got <an integer of about 5001 digits>"),
    (("ports", "inputs", 0, "direction"), [10**400, 0, 0], r"'ports.inputs\[0\].direction'"),
    (("ports", "inputs", 0, "direction"), None, r"'ports.inputs\[0\].direction': got None"),
    (("ports", "inputs", 0, "direction"), [1e300, 1e300, 0], r"squared length is a finite"),
    (("regions",), {"r": {"kind": "box", "lower": None, "upper": [1, 1, 1]}},
     r"'regions.r.lower': got None"),
    (("regions",), {"r": {"kind": "plane", "point": [0, 0, 0], "normal": None}},
     r"'regions.r.normal': got None"),
    (("mesh", "order"), 2.0, r"'mesh.order': got 2.0, expected one of 1 \| 2"),
    (("constraints",), False, r"'constraints': got False, expected a mapping"),
    (("modes",), [], r"'modes': got \[\], expected a mapping"),
    (("name",), _nest(3000, "list"), r"'name': got \[\[\[\[\.\.\.\]\]\]\]"),
    (("name",), _laughs(30), r"'name': got \["),
    (("geometry",), {"kind": "step", "path": "a" * 5000}, r"'geometry.path'.*an existing file"),
    (("geometry",), {"kind": "step", "path": "a\x00b"}, r"'geometry.path'.*a file path"),
    (("damping",), {"kind": "per_mode", "ratios": [10**400] * 4}, r"'damping.ratios\[0\]'"),
]


@pytest.mark.parametrize("path, value, message", REGRESSIONS,
                         ids=[f"{'.'.join(map(str, r[0]))}-{i}" for i, r in enumerate(REGRESSIONS)])
def test_regressions_found_by_fuzzing(path, value, message):
    raw = copy.deepcopy(BASE)
    _set(raw, path, value)
    with pytest.raises(ConfigError, match=message) as info:
        config_from_dict(raw)
    assert len(str(info.value)) < 400


@pytest.mark.parametrize("text, message", [
    ("name: " + "9" * 5000 + "\n", "an integer of more than 4300 digits"),
    ("name: " + "[" * 3000 + "]" * 3000 + "\n", "nested too deeply"),
    ("name: 2020-02-30\n", "a value cannot be read"),
    ("name: !!python/name:os.system\n", "not valid YAML.*could not determine a constructor"),
], ids=["huge_int", "deep", "bad_date", "python_name"])
def test_yaml_that_pyyaml_cannot_construct(yaml_dir, text, message):
    path = yaml_dir / "r.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_config(path)


# --------------------------------------------------------------------------- the CLI
HOSTILE_FILES = {
    "huge_int": BASE_TEXT.replace("count: 10", "count: " + "9" * 5000),
    "deep": BASE_TEXT + "extra: " + "[" * 3000 + "]" * 3000 + "\n",
    "tag": BASE_TEXT.replace("name: cantilever",
                             f"name: !!python/object/apply:os.mkdir ['{SENTINEL_NAME}']"),
    "laughs": "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{c}: &{c} [{', '.join(['*' + p] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi"))
        + "name: *i\n" + BASE_TEXT.split("\n", 2)[2],
    "nan": BASE_TEXT.replace("rho: 2700.0", "rho: .nan"),
    "unicode_name": BASE_TEXT.replace("name: cantilever", "name: 名前\u202e"),
    "binary": "\x00\x01\x02 garbage",
}


@pytest.mark.parametrize("kind", sorted(HOSTILE_FILES))
def test_cli_refuses_hostile_files_with_one_line(tmp_path, kind):
    path = tmp_path / f"{kind}.yaml"
    path.write_text(HOSTILE_FILES[kind])
    proc = subprocess.run([sys.executable, "-m", "pipeline", "-q", "run", str(path), "-o",
                           str(tmp_path / "o.h5"), "--mesh-dir", str(tmp_path)],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("error: ")
    assert len(proc.stderr) < 900
    assert not (tmp_path / SENTINEL_NAME).exists() and not (tmp_path / "o.h5").exists()
    COUNTS["cli_refused"] += 1
