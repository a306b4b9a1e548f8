"""pytest plugin of scripts/tolerance_audit.py: the recorder the rewritten tests call."""
from __future__ import annotations

import builtins
import json
import operator
import os
import sys

import numpy as np
import pytest

_OPS = {"<": operator.lt, "<=": operator.le, ">": operator.gt, ">=": operator.ge}


def _scalar(x):
    if isinstance(x, bool) or isinstance(x, np.bool_):
        return None
    if isinstance(x, (int, float, np.integer, np.floating)):
        return float(x)
    try:
        import torch
        if isinstance(x, torch.Tensor) and x.numel() == 1 and x.dtype != torch.bool:
            return float(x)
    except ImportError:
        pass
    if isinstance(x, np.ndarray) and x.size == 1 and x.dtype != bool:
        return float(x.reshape(-1)[0])
    return None


def _integral(x) -> bool:
    if isinstance(x, (bool, np.bool_)):
        return False
    if isinstance(x, (int, np.integer)):
        return True
    dt = getattr(x, "dtype", None)
    return dt is not None and getattr(x, "ndim", 1) == 0 and str(dt).startswith(("int", "uint", "torch.int"))


def _array(x):
    try:
        import torch
        if isinstance(x, torch.Tensor):
            return x.detach().cpu().double().numpy()
    except ImportError:
        pass
    return np.asarray(x, dtype=np.float64)


class Recorder:
    def __init__(self, sites):
        self.sites, self.rec = sites, {}

    def _keep(self, site, value, bound, m, count=False):
        if self.sites is None:   # a worker process: nothing is collected there
            return
        if m is None or not np.isfinite(m):
            m = None
        # a helper's comparison (e.g. `return frac <= bound`) is kept per calling test line
        f, caller = sys._getframe(1), ""
        while f is not None and not f.f_code.co_name.startswith("test"):
            f = f.f_back
        if f is not None and f.f_lineno != self.sites[site]["line"]:
            caller = f"{os.path.basename(f.f_code.co_filename)}:{f.f_lineno}"
        r = self.rec.setdefault(f"{site}@{caller}", dict(n=0, value=value, bound=bound, margin=m,
                                                         caller=caller, count=count))
        r["n"] += 1
        if m is not None and (r["margin"] is None or m < r["margin"]):
            r.update(value=value, bound=bound, margin=m)

    # ordered comparisons: chain(lambda: a, op, site, lambda: b, ...)
    def chain(self, first, *rest):
        a = first()
        result = True
        for i in range(0, len(rest), 3):
            op, site, nxt = rest[i], rest[i + 1], rest[i + 2]
            b = nxt()
            result = _OPS[op](a, b)
            sa, sb = _scalar(a), _scalar(b)
            if self.sites is not None and sa is not None and sb is not None:
                from tolerance_audit import margin
                info = self.sites[site]
                left = info["bound_side"] == "left"
                value, bound = (sb, sa) if left else (sa, sb)
                vop = {"<": ">", "<=": ">=", ">": "<", ">=": "<="}[op] if left else op
                if info["negated"]:
                    vop = {"<": ">=", "<=": ">", ">": "<=", ">=": "<"}[vop]
                self._keep(site, value, bound, margin(value, vop, bound),
                           count=_integral(a) and _integral(b))
            if i + 3 < len(rest) and not result:   # as Python's chained comparison
                return result
            a = b
        return result

    def _ratio(self, site, a, b, rtol, atol):
        try:
            A, B = np.broadcast_arrays(_array(a), _array(b))
            tol = atol + rtol * np.abs(B)
            d = np.abs(A - B)
            r = np.where(d == 0, 0.0, d / np.where(tol > 0, tol, np.inf))
            r = np.where(np.isnan(A) & np.isnan(B), 0.0, r)
            worst = float(np.max(r)) if r.size else 0.0
            self._keep(site, worst, 1.0, (worst - 1.0) if self.sites[site]["negated"] else 1.0 - worst)
        except Exception:   # a shape the recorder cannot read: the test still runs
            pass

    def allclose(self, a, b, rtol=1e-5, atol=1e-8, equal_nan=False, *, _site):
        self._ratio(_site, a, b, rtol, atol)
        return np.allclose(a, b, rtol=rtol, atol=atol, equal_nan=equal_nan)

    def torch_allclose(self, a, b, rtol=1e-5, atol=1e-8, equal_nan=False, *, _site):
        import torch
        self._ratio(_site, a, b, rtol, atol)
        return torch.allclose(a, b, rtol=rtol, atol=atol, equal_nan=equal_nan)

    def assert_allclose(self, actual, desired, rtol=1e-7, atol=0, *args, _site, **kw):
        self._ratio(_site, actual, desired, rtol, atol)
        return np.testing.assert_allclose(actual, desired, rtol, atol, *args, **kw)

    def approx(self, expected, rel=None, abs=None, nan_ok=False, *, _site):
        return _Approx(self, _site, expected, rel, abs, nan_ok)


class _Approx:
    __array_ufunc__ = None
    __array_priority__ = 100

    def __init__(self, rec, site, expected, rel, abs_, nan_ok):
        self.rec, self.site, self.expected = rec, site, expected
        self.inner = pytest.approx(expected, rel=rel, abs=abs_, nan_ok=nan_ok)
        a = 1e-12 if abs_ is None else abs_
        r = (0.0 if abs_ is not None else 1e-6) if rel is None else rel
        self.rtol, self.atol = r, a

    def __eq__(self, actual):
        try:
            A, E = np.broadcast_arrays(_array(actual), _array(self.expected))
            tol = np.maximum(self.rtol * np.abs(E), self.atol)
            d = np.abs(A - E)
            r = np.where(d == 0, 0.0, d / np.where(tol > 0, tol, np.inf))
            worst = float(np.max(r)) if r.size else 0.0
            self.rec._keep(self.site, worst, 1.0, 1.0 - worst)
        except Exception:
            pass
        return self.inner == actual

    def __ne__(self, actual):
        return not self.__eq__(actual)

    def __repr__(self):
        return repr(self.inner)


def pytest_configure(config):
    with open(os.environ["TOL_AUDIT_SITES"]) as f:
        builtins.__tol_audit__ = Recorder(json.load(f))


def pytest_unconfigure(config):
    rec = getattr(builtins, "__tol_audit__", None)
    if rec is not None:
        with open(os.environ["TOL_AUDIT_OUT"], "w") as f:
            json.dump(rec.rec, f)
