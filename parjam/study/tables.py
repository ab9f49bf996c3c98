"""The typed tables of a scene file (parjam.study.scene): getters that validate a TOML value and
name the key in every one-line error, and a final check that no unknown key is left."""

import math

from parjam.errors import ParjamError
from parjam.files import inputs

INT_MAX = 2**63 - 1  # every integer of a scene is stored as a 64-bit integer (HDF5 attributes)


def show(value, width=60):
    """A value as a message shows it: repr, cut to ``width`` characters, on one line."""
    text = inputs.shown(repr(value))
    return text if len(text) <= width else text[:width - 4] + " ..."


class Table:
    """One TOML table: typed getters that name the key in every error, and a final check that
    no unknown key is left."""

    def __init__(self, data, where, path):
        if not isinstance(data, dict):
            raise ParjamError(f"{path}: [{where}] must be a table, got {type(data).__name__}")
        self.data, self.where, self.path = dict(data), where, path
        self.used = set()

    def fail(self, key, why):
        raise ParjamError(f"{self.path}: [{self.where}] {key}: {why}")

    def has(self, key):
        return key in self.data

    def raw(self, key, default=None):
        self.used.add(key)
        return self.data.get(key, default)

    def int(self, key, default=None, lo=None, hi=INT_MAX):
        v = self.raw(key, default)
        if v is None:
            return None
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(key, f"must be an integer, got {show(v)}")
        if lo is not None and v < lo or v > hi:
            self.fail(key, f"must lie in [{lo}, {hi}], got {show(v)}")
        return v

    def float(self, key, default=None, lo=None, hi=None, lo_open=False):
        v = self.raw(key, default)
        if v is None:
            return None
        return self.number(key, v, lo, hi, lo_open)

    def number(self, key, v, lo=None, hi=None, lo_open=False):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(key, f"must be a finite number, got {show(v)}")
        v = float(v)
        if lo is not None and (v < lo or (lo_open and v == lo)):
            self.fail(key, f"must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
        if hi is not None and v > hi:
            self.fail(key, f"must be <= {hi:g}, got {v:g}")
        return v

    def bool(self, key, default=False):
        v = self.raw(key, default)
        if not isinstance(v, bool):
            self.fail(key, f"must be true or false, got {show(v)}")
        return v

    def str(self, key, default=None, choices=None):
        v = self.raw(key, default)
        if v is None:
            return None
        if not isinstance(v, str):
            self.fail(key, f"must be a string, got {show(v)}")
        if choices and v not in choices:
            self.fail(key, f"must be one of {', '.join(choices)}, got {show(v)}")
        return v

    def list(self, key, default=None, kind=None):
        v = self.raw(key, default)
        if v is None:
            return None
        if not isinstance(v, list):
            v = [v]
        if not v:
            self.fail(key, "must not be empty")
        return v

    def numbers(self, key, default=None, lo=None, hi=None, lo_open=False):
        v = self.list(key, default)
        return None if v is None else [self.number(key, x, lo, hi, lo_open) for x in v]

    def strings(self, key, default=None, choices=None):
        v = self.list(key, default)
        if v is None:
            return None
        for x in v:
            if not isinstance(x, str):
                self.fail(key, f"must be a list of strings, got {show(x)}")
            if choices and x not in choices:
                self.fail(key, f"must be among {', '.join(choices)}, got {show(x)}")
        if len(set(v)) != len(v):
            self.fail(key, "lists a value twice")
        return v

    def done(self):
        extra = sorted(set(self.data) - self.used)
        if extra:
            raise ParjamError(f"{self.path}: [{self.where}] unknown key {show(extra[0])}"
                              + (f" (and {len(extra) - 1} more)" if len(extra) > 1 else ""))
