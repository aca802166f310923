"""Property tests (hypothesis): every loader and option parser, on fuzzed input, either returns a
valid result or raises the project's own `InputError` -- never another exception.

CI budget: `FUZZ_EXAMPLES` examples per loader (200, derandomized: the same examples every run);
`benchmarks/fuzz_loaders.py` runs the same properties with >= 10,000 examples each.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scratch import scratch_dir

from closedloop.errors import InputError

FUZZ_EXAMPLES = int(os.environ.get("CLOSEDLOOP_FUZZ_EXAMPLES", "200"))
FUZZ = settings(
    max_examples=FUZZ_EXAMPLES, derandomize=True, deadline=None, database=None, suppress_health_check=list(HealthCheck)
)
_DIR = scratch_dir("fuzz-")

# ----------------------------------------------------------------------------- value strategies
special_floats = st.sampled_from(
    [
        0.0,
        -0.0,
        1e308,
        -1e308,
        1e-308,
        float("nan"),
        float("inf"),
        -float("inf"),
        1e6,
        1e7,
        3.14159,
        -1.5708,
        2**63,
        10**400,
    ]
)
numbers = st.one_of(st.integers(-(10**6), 10**6), st.floats(allow_nan=True, allow_infinity=True), special_floats)
number_texts = st.one_of(
    numbers.map(lambda v: repr(v) if not isinstance(v, int) or abs(v) < 10**30 else str(v)),
    st.sampled_from(
        [
            "1_000",
            "0x10",
            "1e",
            "--1",
            "+.5",
            ".",
            "nan",
            "-inf",
            "Infinity",
            "1,5",
            " 2 ",
            "",
            "1e400",
            "0b1",
            "1:20",
            "１２",
            "\u00a01",
            "1e-400",
            "true",
            "no",
            "NaN",
        ]
    ),
    st.text(max_size=8),
)
scalars = st.one_of(
    st.none(),
    st.booleans(),
    numbers,
    st.text(max_size=12),
    st.sampled_from(["no", "yes", "on", "off", "m", "in", "deg", "rad", "dh", "hayati", "j1"]),
)
json_values = st.recursive(
    scalars,
    lambda ch: st.one_of(st.lists(ch, max_size=4), st.dictionaries(st.text(max_size=8), ch, max_size=4)),
    max_leaves=12,
)

DH_FIELDS = ["name", "theta_off", "s", "a", "alpha", "k", "lower", "upper", "convention"]


VALID_DH = {
    "name": "chain",
    "closes": False,
    "units": {"length": "m", "angle": "rad"},
    "joints": [
        {"name": "j1", "theta_off": 0.0, "s": 0.3, "a": 0.0, "alpha": 1.5708},
        {"name": "j2", "theta_off": 0.1, "s": 0.0, "a": 0.4, "alpha": 0.0, "convention": "hayati"},
        {"name": "j3", "s": 0.0, "a": 0.2, "alpha": 0.0, "k": 0.95, "lower": -3.0, "upper": 3.0},
    ],
}


@st.composite
def dh_documents(draw):
    """A valid D-H table with 0-3 mutations (a value replaced by anything, a key dropped or added)."""
    if draw(st.integers(0, 9)) == 0:
        return draw(json_values)
    doc = json.loads(json.dumps(VALID_DH))
    for _ in range(draw(st.integers(0, 3))):
        target = (
            doc
            if draw(st.integers(0, 2)) == 0 or not isinstance(doc.get("joints"), list) or not doc["joints"]
            else draw(st.sampled_from(doc["joints"]))
        )
        if not isinstance(target, dict):
            continue
        what = draw(st.integers(0, 3))
        keys = sorted(target) or ["x"]
        if what == 0 and target:
            target.pop(draw(st.sampled_from(keys)))
        elif what == 1:
            target[draw(st.sampled_from(DH_FIELDS + ["units", "closes", "joints"]) | st.text(max_size=4))] = draw(
                json_values
            )
        else:
            target[draw(st.sampled_from(keys))] = draw(st.one_of(numbers, scalars) if what == 2 else json_values)
    return doc


def _yaml_text(doc) -> str:
    try:
        return yaml.safe_dump(doc, allow_unicode=True)
    except (yaml.YAMLError, ValueError, OverflowError):
        return repr(doc)


yaml_texts = st.one_of(
    dh_documents().map(_yaml_text),
    st.text(max_size=200),
    dh_documents().map(_yaml_text).map(lambda t: t.replace("'", "")),
)


@st.composite
def csv_texts(draw):
    """Logs: a header of joint names (some unknown, duplicated or 'loop'), rows of fuzzed cells."""
    names = ["j1", "j2", "j3", "loop", "tau:j1", "x"]
    if draw(st.integers(0, 2)) == 0:  # a well-formed log, so that every run also exercises the loading path
        header = draw(st.lists(st.sampled_from(["j1", "j2", "j3"]), min_size=1, max_size=3, unique=True))
        rows = draw(
            st.lists(
                st.lists(st.floats(-10.0, 10.0).map(repr), min_size=len(header), max_size=len(header)),
                min_size=1,
                max_size=5,
            )
        )
        return "\n".join([",".join(header)] + [",".join(r) for r in rows])
    header = draw(st.lists(st.sampled_from(names) | st.text(max_size=4), min_size=0, max_size=5))
    rows = draw(
        st.lists(
            st.lists(number_texts | st.sampled_from(["fixture", "weld", ""]), min_size=0, max_size=len(header) + 1),
            max_size=5,
        )
    )
    text = "\n".join([",".join(header)] + [",".join(r) for r in rows])
    if draw(st.booleans()):
        text = "\ufeff" + text
    if draw(st.integers(0, 9)) == 0:
        text = draw(st.text(max_size=100))
    return text


@st.composite
def truth_and_report(draw):
    """Truth and report documents close to real ones, with fuzzed names, kinds, units and values."""
    if draw(st.integers(0, 6)) == 0:
        return draw(json_values), draw(json_values)
    names = ["j1.x", "j1.rx", "j1.offset", "f.rx", "f.ry", "f.rz", "j2.s", "j1.scale"]
    if draw(st.integers(0, 2)) == 0:  # well-formed documents, so that every run also exercises the checking path
        chosen = draw(st.lists(st.sampled_from(names), min_size=1, max_size=4, unique=True))
        value = st.floats(-1.0, 1.0)
        truth = {"parameters": {n: draw(value) for n in chosen}}
        return truth, {
            "parameters": [
                {
                    "name": n,
                    "kind": "offset",
                    "unit": "rad",
                    "initial": 0.0,
                    "calibrated": draw(value),
                    "status": "estimated",
                }
                for n in chosen
            ]
        }
    truth = {
        "parameters": draw(
            st.dictionaries(st.sampled_from(names) | st.text(max_size=4), st.one_of(numbers, scalars), max_size=6)
        )
    }
    params = []
    for _ in range(draw(st.integers(0, 6))):
        p = {
            "name": draw(st.sampled_from(names) | scalars),
            "kind": draw(st.sampled_from(["placement", "offset", "scale", "dh", "loop", "compliance"]) | scalars),
            "unit": draw(st.sampled_from(["m", "rad", "1", "px", "rad/Nm"]) | scalars),
            "initial": draw(st.one_of(numbers, scalars)),
            "calibrated": draw(st.one_of(numbers, json_values)),
            "status": draw(st.sampled_from(["estimated", "dropped", "fixed"]) | scalars),
        }
        for k in list(p):
            if draw(st.integers(0, 7)) == 0:
                del p[k]
        params.append(p)
    return truth, {"parameters": params if draw(st.integers(0, 9)) else draw(json_values)}


# ----------------------------------------------------------------------------- properties
def _only_input_errors(fn, *args):
    """fn(*args), or None when it raises the project's InputError (any other exception fails the test)."""
    try:
        return fn(*args)
    except InputError as exc:
        assert str(exc).strip(), repr(exc)  # a message (the CLI prints it on one line)
        return None


def dh_property(text: str) -> None:
    from closedloop.model.robot import RobotModel

    path = _DIR / "fuzz.yaml"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    robot = _only_input_errors(RobotModel.from_file, path)
    if robot is not None:  # a table that loads gives a usable model
        assert robot.model.nq == len(robot.dh.rows)
        assert all(np.isfinite(r.s) and np.isfinite(r.alpha) and r.lower <= r.upper for r in robot.dh.rows)
    return "loaded" if robot is not None else "refused"


def log_property(text: str) -> None:
    from closedloop.io.logs import read_log

    path = _DIR / "fuzz.csv"
    path.write_bytes(text.encode("utf-8", errors="surrogatepass"))
    log = _only_input_errors(read_log, path, ["j1", "j2", "j3"])
    if log is not None:
        assert np.all(np.isfinite(log.angles)) and log.angles.shape[0] >= 1
        assert all(j in ("j1", "j2", "j3") for j in log.joints)
    return "loaded" if log is not None else "refused"


def check_property(docs) -> None:
    from closedloop.validation.check import check_report

    truth, report = docs
    out = _only_input_errors(check_report, truth, report, 1e-3, 5e-3, 5e-3, 1.0)
    if out is not None:
        rows, ok = out
        assert isinstance(ok, bool) and all(r["result"] for r in rows)
    return "loaded" if out is not None else "refused"


def json_property(text: str) -> None:
    from closedloop.io.schemas import load_json

    path = _DIR / "fuzz.json"
    path.write_bytes(text.encode("utf-8", errors="surrogatepass"))
    return "loaded" if _only_input_errors(load_json, path, "JSON file") is not None else "refused"


def options_property(args) -> None:
    from closedloop.cli.parse import check_loop_numbers as _check_loop_numbers
    from closedloop.cli.parse import sim_overrides as _sim_overrides
    from closedloop.io.schemas import parse_bounds as _parse_bounds
    from closedloop.io.schemas import parse_noise as _parse_noise
    from closedloop.sims import SCENARIOS  # the registry with the shipped scenario files

    noise, bound, setting, loop = args
    v = _only_input_errors(_parse_noise, noise)
    if v is not None:
        vals = v.values() if isinstance(v, dict) else [v]
        assert all(0 < x <= 10 for x in vals)
    b = _only_input_errors(_parse_bounds, [bound])
    if b is not None:
        assert all(lo <= hi for lo, hi in b.values())
    s = _only_input_errors(_sim_overrides, [setting], SCENARIOS["panda_weld"].settings)
    _only_input_errors(_check_loop_numbers, loop)
    return "loaded" if b is not None or v is not None or s is not None else "refused"


settings_items = st.one_of(
    st.tuples(
        st.sampled_from(
            [
                "kp",
                "kv",
                "timestep",
                "noise",
                "select",
                "solref",
                "solimp",
                "gravity",
                "min_steps",
                "max_steps",
                "integrator",
                "stiff",
                "relax_passes",
                "bogus",
                "",
            ]
        ),
        st.sampled_from(["=", ":", "=="]),
        number_texts
        | st.sampled_from(
            [
                "[1,2]",
                "[0.9,0.95,0.001,0.5,2]",
                "[1]",
                "true",
                "greedy",
                "bogus",
                "null",
                "[nan,1]",
                "[1e308, 1]",
                "{}",
                "[true,1]",
            ]
        ),
    ).map("".join),
    st.text(max_size=20),
)
option_args = st.tuples(
    st.one_of(
        number_texts,
        st.lists(st.tuples(st.sampled_from(["j1", "", "*"]), number_texts).map("=".join), max_size=3).map(",".join),
    ),
    st.tuples(
        st.sampled_from(["x", "", "j1.x"]),
        st.sampled_from(["=", ""]),
        number_texts,
        st.sampled_from([":", ""]),
        number_texts,
    ).map("".join),
    settings_items,
    st.tuples(
        st.sampled_from(["weld:frame=a,closure=", "point:point="]), st.lists(number_texts, max_size=6).map(" ".join)
    ).map(lambda t: f'{t[0]}"{t[1]}"'),
)

PROPERTIES = {
    "dh": (dh_property, yaml_texts),
    "log": (log_property, csv_texts()),
    "check": (check_property, truth_and_report()),
    "json": (json_property, st.one_of(st.text(max_size=60), json_values.map(lambda v: json.dumps(v, allow_nan=True)))),
    "options": (options_property, option_args),
}


def run_property(name: str, max_examples: int = FUZZ_EXAMPLES) -> dict[str, int]:
    """Run property `name` on `max_examples` derandomized examples; count the outcomes."""
    from collections import Counter

    prop, strategy = PROPERTIES[name]
    counts: Counter = Counter()

    @settings(FUZZ, max_examples=max_examples)
    @given(strategy)
    def run(x):
        counts[prop(x)] += 1

    run()
    return dict(counts)


@pytest.mark.parametrize("name", sorted(PROPERTIES))
def test_fuzz_loader(name):
    """Zero exceptions other than InputError; and the fuzzer reaches both outcomes (it is not trivial)."""
    counts = run_property(name)
    assert counts.get("loaded", 0) > 0 and counts.get("refused", 0) > 0, counts
