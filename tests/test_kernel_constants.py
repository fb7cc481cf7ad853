"""Warp evaluates arithmetic of Python constants inside a kernel in float32, whatever it is
then cast to: ``scalar(C * C)`` with a module-level ``C = 0.95`` is ``0.9025 - 2.6e-8`` in a
float64 kernel, where ``scalar(C)`` alone, ``scalar(C) * scalar(C)`` and a constant computed in
Python before the kernel (``c2 = scalar(C * C)`` in the factory) are exact. So a float64 model
silently takes float32 constants wherever a kernel combines Python numbers. This reads the
source of every ``wp.func``/``wp.kernel`` in the package and the benchmarks' MPM reference
for such expressions."""

import ast
import importlib
import math
import pathlib
import pkgutil

import warp_esph

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _modules():
    """``(module globals, source path)`` of each module with kernels."""
    for info in pkgutil.walk_packages(warp_esph.__path__, "warp_esph."):
        if info.name.endswith("__main__"):  # runs the command line
            continue
        mod = importlib.import_module(info.name)
        yield vars(mod), pathlib.Path(mod.__file__)
    yield vars(importlib.import_module("benchmarks.mpm_slump")), ROOT / "benchmarks" / "mpm_slump.py"


def _is_warp_function(fn: ast.FunctionDef) -> bool:
    return any(ast.unparse(d).startswith("wp.") for d in fn.decorator_list)


def _locals(fn: ast.FunctionDef) -> set:
    names = {a.arg for a in fn.args.args}
    for node in ast.walk(fn):
        if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
    return names


def _python_number(node, glb: dict, local: set):
    """Whether ``node`` is a Python number the kernel sees as a constant (a literal, a
    module-level number, ``math.pi``, ...): ``"float"``, ``"int"`` or None."""
    if isinstance(node, ast.Constant) and type(node.value) in (int, float):
        return type(node.value).__name__
    if isinstance(node, ast.Name) and node.id not in local and type(glb.get(node.id)) in (int, float):
        return type(glb[node.id]).__name__
    if isinstance(node, ast.Attribute) and ast.unparse(node.value) == "math" and isinstance(
            getattr(math, node.attr, None), float):
        return "float"
    if isinstance(node, ast.UnaryOp):
        return _python_number(node.operand, glb, local)
    return None


def _constant_arithmetic(node, glb: dict, local: set) -> bool:
    """Whether ``node`` is arithmetic (or a ``math`` function) of Python numbers only, one of
    them a float (integer arithmetic Warp does exactly)."""
    if isinstance(node, ast.BinOp):
        kinds = []
        for side in (node.left, node.right):
            k = _python_number(side, glb, local)
            if k is None:
                if not _constant_arithmetic(side, glb, local):
                    return False
                k = "float"
            kinds.append(k)
        return "float" in kinds or isinstance(node.op, ast.Div)
    if isinstance(node, ast.Call) and ast.unparse(node.func).startswith("math.") and node.args:
        return all(_python_number(a, glb, local) or _constant_arithmetic(a, glb, local) for a in node.args)
    return False


def constant_arithmetic_sites() -> list[str]:
    """``path:line: expression`` of each arithmetic of Python numbers inside a kernel."""
    sites = []
    for glb, path in _modules():
        tree = ast.parse(path.read_text())
        for fn in ast.walk(tree):
            if not (isinstance(fn, ast.FunctionDef) and _is_warp_function(fn)):
                continue
            local = _locals(fn)
            seen = set()
            for node in ast.walk(fn):
                if id(node) in seen or not _constant_arithmetic(node, glb, local):
                    continue
                seen.update(id(n) for n in ast.walk(node))
                sites.append(f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}")
    return sites


def test_no_kernel_combines_python_numbers_by_arithmetic():
    """No kernel computes a constant from Python numbers (``scalar(C * C)``, ``scalar(1.0 /
    3.0)``, ``math.sqrt(2.0)``): compute it in Python outside the kernel and cast it once
    (``c2 = scalar(C * C)`` in the factory), so that a float64 kernel takes it in float64."""
    sites = constant_arithmetic_sites()
    assert not sites, "kernels that compute a constant from Python numbers in float32:\n" + "\n".join(sites)


def test_the_check_finds_constant_arithmetic(tmp_path):
    """The check sees what it is for, and leaves casts of single constants and arithmetic of
    typed values alone."""
    src = '''
import math
import warp as wp
C = 0.95
N = 3

@wp.func
def f(x: float, n: int):
    a = wp.float64(C * C) * x
    b = wp.float64(1.0 / 3.0)
    c = wp.float64(math.sqrt(2.0))
    d = wp.float64(-C) * wp.float64(C) + wp.float64(math.pi) * x
    e = n * N + (N - 1)
    return a + b + c + d
'''
    tree = ast.parse(src)
    glb = {"C": 0.95, "N": 3}
    fn = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef))
    local = _locals(fn)
    found = sorted({ast.unparse(n) for n in ast.walk(fn) if _constant_arithmetic(n, glb, local)})
    assert found == ["1.0 / 3.0", "C * C", "math.sqrt(2.0)"]
