"""Hostile input to the scene parser (parjam.study.scene) and to ``parjam run``, property-based.

Properties:
- ``scene.loads`` of arbitrary text, and ``scene.parse`` of a valid scene with one value replaced
  by something hostile (wrong type, NaN/inf, negative, zero, huge, a nested table, an unknown
  key), either returns a Scene or raises ParjamError: never another exception;
- the replacements that break a rule the parser documents (d outside {2, 3}, N below 16 or not an
  integer, non-positive or non-finite dphi, members < 1, an unknown key) are always refused, with
  a message that names the key;
- ``parjam run`` of a hostile scene file ends with one ``parjam: error:`` line, a non-zero
  status, and creates no output directory.

Examples are derandomised so that both ranks of the MPI pass draw the same ones.
"""

import copy
import math
import os
import tomllib

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from parjam.study import scene
from parjam.errors import ParjamError

from test_hostile import EXAMPLES, assert_clean_error, run_cli, workdir

HOSTILE = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                   suppress_health_check=[HealthCheck.too_slow])

VALID = """
[[system]]
d = 3
N = 64
[protocol]
dphi = [1e-4, 1e-2]
[ensemble]
members = 2
seed = 3
[observables]
contacts = true
dos = { matrices = ["full"], bins = 20 }
"""

# (table path, key): where a hostile value goes
PLACES = [(("system", 0), "d"), (("system", 0), "N"), (("system", 0), "alpha"),
          (("system", 0), "ratio"), (("system", 0), "dispersity"), (("protocol",), "dphi"),
          (("protocol",), "ftol"), (("protocol",), "ladder"), (("ensemble",), "members"),
          (("ensemble",), "seed"), (("observables",), "dos"), (("observables",), "contacts")]

HOSTILE_VALUES = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, 0, -1, -1e300, 1e300, 10**30, True, "",
                     "mono", [], [math.nan], [0.0], [-1e-3], [1e-3, 1e-3], {}, {"x": 1},
                     [[1]], 3.5, 1, 4, 15]),
    st.integers(), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4))


def _with(data, place, key, value):
    out = copy.deepcopy(data)
    table = out
    for part in place:
        table = table[part]
    table[key] = value
    return out


def _must_refuse(place, key, value):
    """Values the parser's documented rules forbid (a subset of all refusals)."""
    num = isinstance(value, (int, float)) and not isinstance(value, bool)
    if key == "d":
        return not (num and isinstance(value, int) and value in (2, 3))
    if key == "N":
        return not (isinstance(value, int) and not isinstance(value, bool) and 16 <= value)
    if key == "members":
        return not (isinstance(value, int) and not isinstance(value, bool) and value >= 1)
    if key == "dphi":
        vals = value if isinstance(value, list) else [value]
        return (not vals or any(isinstance(v, bool) or not isinstance(v, (int, float))
                                or not math.isfinite(v) or v <= 0 for v in vals))
    if key == "alpha":
        return not (num and math.isfinite(value) and value > 1)
    return False


@HOSTILE
@given(place_key=st.sampled_from(PLACES), value=HOSTILE_VALUES)
def test_parse_hostile_values(place_key, value):
    place, key = place_key
    data = _with(tomllib.loads(VALID), place, key, value)
    try:
        scene.parse(data, "hostile.toml")
    except ParjamError as exc:
        msg = str(exc)
        assert "\n" not in msg and msg.startswith("hostile.toml")
        if _must_refuse(place, key, value):
            assert key in msg, msg
        return
    assert not _must_refuse(place, key, value), f"{key} = {value!r} was accepted"


@HOSTILE
@given(where=st.sampled_from(["", "system", "protocol", "ensemble", "observables"]),
       key=st.text(alphabet="abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=10))
def test_unknown_keys_are_named(where, key):
    data = tomllib.loads(VALID)
    table = data if not where else (data["system"][0] if where == "system" else data[where])
    if key in table or (where == "" and key in ("scene", "solver")):
        return
    table[key] = 1
    with pytest.raises(ParjamError) as info:
        scene.parse(data, "s.toml")
    assert key in str(info.value)


@HOSTILE
@given(text=st.text(max_size=200))
def test_loads_arbitrary_text(text):
    try:
        scene.loads(text, "t.toml")
    except ParjamError as exc:
        assert str(exc).startswith("t.toml")


@pytest.mark.parametrize("content", [
    b"\x89HDF\r\n\x1a\n\x00\x00binary",          # not TOML at all
    VALID.replace("d = 3", "d = 4").encode(),     # d outside {2, 3}
    VALID.replace("N = 64", "N = -5").encode(),   # negative N
    VALID.replace("[1e-4, 1e-2]", "[nan]").encode(),  # NaN dphi
    VALID.replace("members = 2", "members = 0").encode(),
    VALID.replace("contacts = true", "contacts = true\ncolour = 3").encode(),  # unknown key
    b"",                                          # empty file
])
def test_run_refuses_hostile_scene(content):
    with workdir() as tmp:
        path = os.path.join(tmp, "scene.toml")
        with open(path, "wb") as fh:
            fh.write(content)
        out = os.path.join(tmp, "out")
        rc, _, err = run_cli(["run", path, "--out", out, "-q"])
        assert_clean_error(rc, err, [out])
        rc, _, err = run_cli(["run", path, "--dry-run"])
        assert_clean_error(rc, err)
