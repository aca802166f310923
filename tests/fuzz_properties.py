"""The fuzzing properties (hypothesis): every loader and option parser, on fuzzed input, either returns a
valid result or raises the project's own `InputError` -- never another exception.

`tests/test_fuzz_loaders.py` runs them in CI (`FUZZ_EXAMPLES` examples per loader, 200, derandomized: the same
examples every run); `benchmarks/fuzz_loaders.py` runs them with >= 10,000 examples each.  A module of its own,
not a test file: collecting the suite imports no hypothesis.
"""

from __future__ import annotations

import json
import os

import numpy as np
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
    from closedloop.cli.parse import sim_overrides as _sim_overrides
    from closedloop.run.options import check_loop_numbers as _check_loop_numbers
    from closedloop.run.options import parse_bounds as _parse_bounds
    from closedloop.run.options import parse_noise as _parse_noise
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

# ----------------------------------------------------------------------------- manifests, configs, robot files, bags
MANIFEST_KEYS = ["name", "model", "log", "out", "loops", "cv", "noise", "snr", "max_iter", "weighting", "robust"]
MANIFEST_KEYS += ["degrees", "fix", "bounds", "identify", "options", "robot", "date", "gap"]


@st.composite
def manifests(draw):
    """Batch manifests (YAML text): a valid job with fuzzed values in some keys, or fuzzed documents."""
    if draw(st.integers(0, 7)) == 0:
        return draw(st.text(max_size=80))
    jobs = []
    for i in range(draw(st.integers(0, 3))):
        job = {"name": f"j{i}", "model": "m.urdf", "log": "l.csv", "out": f"o/j{i}"}
        for _ in range(draw(st.integers(0, 3))):
            key = draw(st.sampled_from(MANIFEST_KEYS))
            job[key] = draw(st.one_of(scalars, json_values, number_texts))
        if draw(st.integers(0, 9)) == 0:
            job["name"] = "j0"  # a duplicate name
        jobs.append(job)
    doc = {"defaults": draw(st.one_of(st.just({}), json_values)) if draw(st.booleans()) else {}, "jobs": jobs}
    return yaml.safe_dump(doc) if draw(st.integers(0, 9)) else yaml.safe_dump(draw(json_values))


def manifest_property(text: str) -> str:
    from closedloop.fleet.manifest import read_manifest

    path = _DIR / "fuzz.yaml"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    jobs = _only_input_errors(read_manifest, path)
    if jobs is not None:  # every job: unique name, a whole number of folds, checked options
        assert len({j.name for j in jobs}) == len(jobs) and all(j.cv is None or j.cv == 0 or j.cv >= 2 for j in jobs)
        for j in jobs:
            for k in ("snr", "max_iter"):
                assert k not in j.options or (np.isfinite(j.options[k]) and j.options[k] > 0)
            assert "degrees" not in j.options or isinstance(j.options["degrees"], bool)
    return "loaded" if jobs is not None else "refused"


CONFIG_KEYS = ["report", "out", "snr", "cv", "max-iter", "noise", "loop", "fix", "bound", "degrees", "weighting"]


def config_property(doc) -> str:
    """A calibrate --config (the parser only: no calibration runs) is applied or refused in one line."""
    import argparse

    from closedloop.cli.config import load_config
    from closedloop.cli.main import build_parser

    path = _DIR / "config.yaml"
    path.write_text(yaml.safe_dump(doc) if not isinstance(doc, str) else doc, encoding="utf-8", errors="surrogatepass")
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices["calibrate"]
    cfg = _only_input_errors(load_config, str(path), sub, "calibrate")
    if cfg is not None:
        for k in ("report", "out"):
            assert cfg.get(k) is None or isinstance(cfg[k], str)
        assert cfg.get("degrees") in (None, True, False)
    return "loaded" if cfg is not None else "refused"


config_docs = st.one_of(
    st.dictionaries(st.sampled_from(CONFIG_KEYS), st.one_of(scalars, json_values, number_texts), max_size=4),
    st.text(max_size=40),
)

URDF_PARTS = {
    "xyz": ["0 0 0.1", "nan 0 0", "0 inf 0", "1 2", "${a} 0 0", "1e400 0 0", "a b c", ""],
    "axis": ["0 0 1", "0 0 0", "1 0 0", "nan 0 1", "0 1"],
    "type": ["revolute", "continuous", "prismatic", "fixed", "bogus", ""],
    "parent": ["base", "l1", "l2", "l9", ""],
    "child": ["l1", "l2", "base", "l9", ""],
}


@st.composite
def urdf_texts(draw):
    """Small URDFs: up to 4 joints between links base, l1, l2 with fuzzed origins, axes, types, ends."""
    links = "".join(f'<link name="{n}"/>' for n in draw(st.lists(st.sampled_from(["base", "l1", "l2"]), max_size=4)))
    joints = ""
    for i in range(draw(st.integers(0, 4))):
        v = {k: draw(st.sampled_from(opts)) for k, opts in URDF_PARTS.items()}
        name = draw(st.sampled_from([f"j{i}", "j0"]))
        joints += (
            f'<joint name="{name}" type="{v["type"]}"><parent link="{v["parent"]}"/><child link="{v["child"]}"/>'
            f'<origin xyz="{v["xyz"]}"/><axis xyz="{v["axis"]}"/>'
            '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
        )
    text = f'<robot name="r">{links}{joints}</robot>'
    if draw(st.integers(0, 9)) == 0:
        k = draw(st.integers(0, len(text)))
        text = text[:k] + draw(st.text(max_size=6)) + text[k:]
    return text


def urdf_property(text: str) -> str:
    from closedloop.model.robot import RobotModel

    path = _DIR / "fuzz.urdf"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    robot = _only_input_errors(RobotModel.from_file, path)
    if robot is not None:
        assert all(np.linalg.norm(j.axis) > 0.5 for j in robot.joints.values())
    return "loaded" if robot is not None else "refused"


_BAGS: dict[str, bytes] = {}


def _clean_bag(fmt: str) -> bytes:
    """A small ROS 1 or MCAP bag of 3 standstills of 3 joints (written once)."""
    if fmt not in _BAGS:
        from rosbags.typesys import Stores, get_typestore

        store = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
        js = "sensor_msgs/msg/JointState"
        JointState, Header = store.types[js], store.types["std_msgs/msg/Header"]
        Time = store.types["builtin_interfaces/msg/Time"]
        d = scratch_dir("bag-")
        if fmt == "ros1":
            from rosbags.rosbag1 import Writer

            path, writer = d / "b.bag", None
            writer = Writer(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            path = d / "b"
            writer = Writer(path, version=8, storage_plugin=StoragePlugin.MCAP)
        with writer:
            conn = writer.add_connection("/joint_states", js, typestore=store)
            for k in range(300):  # 3 s at 100 Hz: three 1 s standstills
                t_ns = 10**18 + k * 10**7
                hdr = Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9)
                h = Header(seq=k, stamp=hdr, frame_id="") if fmt == "ros1" else Header(stamp=hdr, frame_id="")
                q = np.full(3, float(k // 100))
                msg = JointState(
                    header=h, name=["j1", "j2", "j3"], position=q, velocity=np.zeros(3), effort=np.zeros(0)
                )
                raw = store.serialize_ros1(msg, js) if fmt == "ros1" else store.serialize_cdr(msg, js)
                writer.write(conn, t_ns, raw)
        f = path if path.is_file() else next(path.glob("*.mcap"))
        _BAGS[fmt] = f.read_bytes()
    return _BAGS[fmt]


@st.composite
def garbled_bags(draw):
    fmt = draw(st.sampled_from(["ros1", "mcap"]))
    data = bytearray(_clean_bag(fmt))
    for _ in range(draw(st.integers(0, 3))):
        k = draw(st.integers(0, len(data) - 1))
        n = draw(st.sampled_from([1, 8, 64, 4096]))
        data[k : k + n] = draw(st.binary(min_size=min(n, len(data) - k), max_size=min(n, len(data) - k)))
    return fmt, bytes(data)


def bag_property(case) -> str:
    from closedloop.io.bags import extract

    fmt, data = case
    path = _DIR / ("fuzz.bag" if fmt == "ros1" else "fuzz.mcap")
    path.write_bytes(data)
    out = _only_input_errors(extract, path, ["j1", "j2", "j3"])
    if out is not None:
        lg, _ = out
        assert np.all(np.isfinite(lg.angles)) and lg.angles.shape[1] == 3
    return "loaded" if out is not None else "refused"


PROPERTIES = {
    "dh": (dh_property, yaml_texts),
    "log": (log_property, csv_texts()),
    "check": (check_property, truth_and_report()),
    "json": (json_property, st.one_of(st.text(max_size=60), json_values.map(lambda v: json.dumps(v, allow_nan=True)))),
    "options": (options_property, option_args),
    "manifest": (manifest_property, manifests()),
    "config": (config_property, config_docs),
    "urdf": (urdf_property, urdf_texts()),
    "bag": (bag_property, garbled_bags()),
}
#: examples per property in the test (the bag reader is slower: fewer)
TEST_EXAMPLES = {"bag": max(1, FUZZ_EXAMPLES // 5)}


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
