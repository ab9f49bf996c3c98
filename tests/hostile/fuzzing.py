"""Shared pieces of the fuzz tests (test_fuzz.py, test_fuzz_importers.py): the example counts of
the short (CI) and long profiles, and a TOML writer for generated scenes.

Profiles: the CI runs ``FUZZ_EXAMPLES`` examples per property (a few hundred over all
properties, well under a minute); ``scripts/fuzz.py --examples N`` runs N per property (the
long profile) through ``PARJAM_FUZZ_EXAMPLES``.  Examples are derandomised, so that both ranks
of the MPI pass draw the same ones (the in-process command line is collective), and no example
database is written (tests write only in their own temporary directories).
"""

import json
import math
import os
import re

from hypothesis import HealthCheck, settings

FUZZ_EXAMPLES = int(os.environ.get("PARJAM_FUZZ_EXAMPLES", "40"))


def profile(weight=1.0):
    """Hypothesis settings of one property: ``weight`` x the profile's example count."""
    return settings(max_examples=max(int(FUZZ_EXAMPLES * weight), 1), deadline=None,
                    derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.filter_too_much])


_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def toml_key(key):
    return key if _BARE.match(key) else json.dumps(key)


def toml_value(value):
    """A TOML value for a Python one (str, bool, int, float, list, dict), inline."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        # JSON's escapes (\uXXXX for control characters) are TOML basic-string escapes too;
        # a lone surrogate cannot be written in UTF-8 at all: replaced
        return json.dumps(value.encode("utf-8", "replace").decode("utf-8"))
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{toml_key(k)} = {toml_value(v)}" for k, v in value.items()) \
            + "}"
    raise TypeError(type(value))


def toml_document(top):
    """A TOML document of a dict: one ``key = inline value`` line per top-level key."""
    return "".join(f"{toml_key(k)} = {toml_value(v)}\n" for k, v in top.items())
