"""Every kernel is its own Warp module (docs/method.md, "CPU device"), the tests' own kernels
and those of the benchmarks and examples the tests run included. A module's hash covers every
kernel registered in it, so a kernel that a test (or a cached factory) defines into a shared
module makes that module's next launch compile all of its kernels again: the 19 tests of
``test_shared_formulas.py`` compiled their file's module 19 times, each time larger (53-60 s
of compiling in an empty kernel cache against 10.3-12.4 s as one module per kernel:
docs/performance.md, "Modules only a test compiles"), and the module's contents, so its
cache entry, depended on which tests a worker had run before."""

import ast
import pathlib

import numpy as np
import pytest
import warp as wp

import test_shared_formulas as sf

ROOT = pathlib.Path(__file__).resolve().parent.parent


def _kernel_decorators(path: pathlib.Path):
    """``(line, keywords)`` of each ``wp.kernel`` decorator in ``path``."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.FunctionDef):
            for d in node.decorator_list:
                call = d if isinstance(d, ast.Call) else None
                target = call.func if call else d
                if isinstance(target, ast.Attribute) and target.attr == "kernel" and \
                        isinstance(target.value, ast.Name) and target.value.id == "wp":
                    yield d.lineno, {k.arg: k.value for k in call.keywords} if call else {}


def test_every_kernel_is_defined_into_a_module_of_its_own():
    """Each ``@wp.kernel`` of the package, the tests, the benchmarks and the examples says
    ``module="unique"``."""
    shared = []
    for folder in ("warp_esph", "tests", "benchmarks", "examples"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for line, keywords in _kernel_decorators(path):
                module = keywords.get("module")
                if not (isinstance(module, ast.Constant) and module.value == "unique"):
                    shared.append(f"{path.relative_to(ROOT)}:{line}")
    assert not shared, f"kernels in a shared module (a new kernel there recompiles them all): {shared}"


def test_a_kernel_defined_later_leaves_a_compiled_one_as_it_was():
    """A test kernel launched, then another test's kernel made: the first's module keeps the
    hash it was compiled under (it would be built again at its next launch otherwise), and it
    still computes the pair viscosity, the mean of the two."""
    first = sf._pair_viscosity_kernel.__wrapped__(wp.float32)
    eta = np.array([1.0, 3.0, 2.0, 6.0], dtype=np.float32)
    out = wp.zeros(2, dtype=wp.float32)
    wp.launch(first, len(out), [wp.array(eta, dtype=wp.float32)], [out])
    before = first.module.get_module_hash()
    sf._flow_kernel.__wrapped__(wp.float32)  # a new kernel object, as a test's factory makes
    assert first.module.get_module_hash() == before
    wp.launch(first, len(out), [wp.array(eta, dtype=wp.float32)], [out])
    np.testing.assert_allclose(out.numpy(), [2.0, 4.0], rtol=0)


@pytest.mark.parametrize("name", ["_pair_viscosity_kernel", "_flow_kernel"])
def test_a_factory_kernel_of_each_precision_is_its_own_module(name):
    """A test's kernel made for float32 and for float64 lands in two modules, neither of
    them the test file's."""
    factory = getattr(sf, name)
    k32, k64 = factory(wp.float32), factory(wp.float64)
    assert k32.module is not k64.module
    assert sf.__name__ not in (k32.module.name, k64.module.name)
