"""Property tests: every loader and option parser, on fuzzed input, either returns a valid result or raises
the project's own `InputError` -- never another exception (the properties: `fuzz_properties`).

The loaders are named here, and hypothesis and the properties imported only when a test runs: these tests
are `slow`, and every run of the default suite collects this file.
"""

from __future__ import annotations

import pytest

#: the properties of `fuzz_properties.PROPERTIES`, one test each
LOADERS = ["bag", "check", "config", "dh", "json", "log", "manifest", "options", "urdf"]


@pytest.mark.slow
@pytest.mark.parametrize("name", LOADERS)
def test_fuzz_loader(name):
    """Zero exceptions other than InputError; and the fuzzer reaches both outcomes (it is not trivial)."""
    from fuzz_properties import FUZZ_EXAMPLES, PROPERTIES, TEST_EXAMPLES, run_property

    assert sorted(PROPERTIES) == LOADERS, "a property without its test (or a test without its property)"
    counts = run_property(name, TEST_EXAMPLES.get(name, FUZZ_EXAMPLES))
    assert counts.get("loaded", 0) > 0 and counts.get("refused", 0) > 0, counts
