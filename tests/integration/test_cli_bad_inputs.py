"""Every bad input of issue 9 through the INSTALLED ``hil`` entry point, as a user meets it:
exit code 2, exactly one line on stderr, naming the file (or option) and the field, no traceback.

One table: (case id, argv, files to create, what the line must contain). Files are written into a
temporary directory; ``{tmp}`` in argv and expectations is replaced by its path.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from tests.integration.bad_input_cases import (
    FD,
    FIFO,
    LAB_PUBLIC_PEM,
    LMPC,
    PD_BUNDLE,
    RUNTIME_YAML,
    SIX,
    Case,
    _bundle_case,
    _condition,
    _conditions_case,
    _plot_case,
    _record_case,
    _run_case,
    _runtime_case,
    _target_case,
    _telemetry_check_case,
    _urdf,
    _urdf_case,
)
from tests.unit.hil_runtime.telemetry import npz_files

# (id, argv, {relative file: text or bytes}, substrings of the one stderr line)
CASES: list[Case] = [
    # conditions
    _conditions_case("payload<0", _condition("    mismatch: {payload_kg: -1}\n"), "mismatch.payload_kg: must be >= 0"),
    _conditions_case("frequency<0", _condition("    frequency_hz: -0.1\n"), "frequency_hz[0]: must be >= 0"),
    _conditions_case(
        "disturbance-late", _condition("    duration_s: 1\n    disturbance: {time_s: 2}\n"), "disturbance.time_s"
    ),
    _conditions_case(
        "inertia_scale=0", _condition("    mismatch: {inertia_scale: 0}\n"), "inertia_scale[0]: must be > 0"
    ),
    _conditions_case("conditions-binary", bytes(range(256)), "not a UTF-8 text file"),
    _conditions_case("conditions-empty", "", "empty file"),
    _conditions_case(
        "conditions-nan",
        "conditions:\n  - name: A\n    amplitude_rad: [.nan, 0, 0, 0, 0, 0]\n",
        "amplitude_rad[0]: not finite",
    ),
    # options
    ("timing-cycles=0", ["experiment", "--timing-cycles", "0"], {}, ["--timing-cycles", "positive"]),
    ("timing-cycles<0", ["experiment", "--timing-cycles", "-3"], {}, ["--timing-cycles", "positive"]),
    ("period_s=0", ["experiment", "--period-s", "0"], {}, ["--period-s", "positive"]),
    ("unknown-option", ["experiment", "--colour", "red"], {}, ["No such option: --colour"]),
    ("unknown-robot", ["experiment", "--robot", "r2d2"], {}, ["robot: unknown name 'r2d2'", "ur5_paper"]),
    ("unknown-executor", ["pipeline", "--executor", "dask"], {}, ["--executor: unknown 'dask'", "serial, local, ray"]),
    ("workers=0", ["pipeline", "--workers", "0"], {}, ["--workers: must be >= 1"]),
    ("unknown-stage", ["pipeline", "--stages", "dataset,fit"], {}, ["--stages: unknown 'fit'", "augment"]),
    (
        "train-realism-unknown",
        ["pipeline", "--train-realism", "stormy"],
        {},
        ["--train-realism: 'stormy'", "realistic"],
    ),
    (
        "train-realism-bad-file",
        ["pipeline", "--train-realism", "{tmp}/p.yaml"],
        {"p.yaml": "sensing:\n  delay_periods: -1\n"},
        ["p.yaml: sensing.delay_periods"],
    ),
    ("realism-draws=0", ["pipeline", "--realism-draws", "0"], {}, ["--realism-draws: must be >= 1"]),
    ("ideal-draws<0", ["pipeline", "--ideal-draws", "-1"], {}, ["--ideal-draws: must be >= 0"]),
    ("envelope-conditions<0", ["pipeline", "--envelope-conditions", "-2"], {}, ["--envelope-conditions: must be >= 0"]),
    (
        "law-coefficient-unknown",
        ["pipeline", "--law-coefficient", "half"],
        {},
        ["--law-coefficient: unknown 'half'", "fitted"],
    ),
    (
        "lmpc-velocity-filter-above-nyquist",
        ["experiment", "--lmpc-velocity-filter-hz", "600"],
        {},
        ["--lmpc-velocity-filter-hz: velocity filter: cutoff 600.0 Hz", "Nyquist rate 500 Hz"],
    ),
    (
        "bundle-check-negative-noise",
        ["bundle", "check", "models/bundles/ur5_paper/pd", "--encoder-noise-rad", "-1"],
        {},
        ["--encoder-noise-rad: must be a finite RMS noise >= 0"],
    ),
    # --out
    ("out-file-in-the-way", ["experiment", "--out", "{tmp}/f"], {"f": "x"}, ["--out {tmp}/f: a file is in the way"]),
    (
        "out-parent-is-a-file",
        ["experiment", "--out", "{tmp}/f/sub/out"],
        {"f": "x"},
        ["{tmp}/f is a file, not a directory"],
    ),
    (
        "out-read-only-fs",
        ["experiment", "--out", "/proc/hil-out"],
        {},
        ["--out /proc/hil-out: cannot create the directory"],
    ),
    # URDF
    _urdf_case("urdf-no-limit", _urdf(r"<limit [^>]*/>", ""), "joint 'shoulder_pan_joint' <limit>: missing"),
    _urdf_case(
        "urdf-prismatic",
        _urdf(r'(<joint name="elbow_joint" type=)"revolute"', r'\1"prismatic"'),
        "'elbow_joint' type 'prismatic'",
    ),
    _urdf_case("urdf-negative-inertia", _urdf(r'ixx="', 'ixx="-'), "<inertia> ixx: negative"),
    _urdf_case("urdf-binary", b"\x89PNG\r\n\x1a\n\x00\x00", "not valid XML"),
    # issue 25 item 4: shapes of URDF the loader refuses (continuous joints are treated as unbounded)
    _urdf_case(
        "urdf-floating-base",
        _urdf(
            r'<link name="base_link"/>',
            '<link name="world"/><joint name="free" type="floating"><parent link="world"/>'
            '<child link="base_link"/></joint><link name="base_link"/>',
        ),
        "joint 'free' type 'floating': a floating base is not supported",
    ),
    _urdf_case(
        "urdf-closed-chain",
        _urdf(
            r'<link name="base_link"/>',
            '<link name="base_link"/><joint name="strut" type="fixed"><parent link="base_link"/>'
            '<child link="forearm_link"/></joint>',
        ),
        "link 'forearm_link' is the child of joints 'strut' and 'elbow_joint': a closed chain",
    ),
    _urdf_case(
        "urdf-mimic",
        _urdf(r'(<joint name="elbow_joint" type="revolute">)', r'\1<mimic joint="shoulder_lift_joint"/>'),
        "joint 'elbow_joint' <mimic>",
    ),
    _urdf_case(
        "urdf-continuous-no-limit",
        _urdf(r'(<joint name="elbow_joint" type=)"revolute"(.*?)<limit [^>]*/>', r'\1"continuous"\2'),
        "joint 'elbow_joint' <limit>: missing",
    ),
    _urdf_case(
        "urdf-massless-tail",
        _urdf(
            r'<mass value="0.4"/>\s*<inertia [^>]*/>',
            '<mass value="0"/><inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/>',
        ),
        "joint 'wrist_3_joint' moves no inertia",
    ),
    _urdf_case("urdf-no-effort", _urdf(r'effort="102" ', ""), "joint 'shoulder_pan_joint' <limit> effort: missing"),
    _target_case(
        "target-unknown-joint",
        {"t.yaml": FD + "plant: {joint_names: [shoulder_pan_joint, thumb_joint]}\n"},
        "plant.joint_names",
        "thumb_joint",
    ),
    # target configs
    _target_case(
        "target-q0-outside",
        {"t.yaml": FD + "plant: {initial_position_rad: [0, 0, 3.0, 0, 0, 0]}\n"},
        "plant.initial_position_rad[2]",
        "outside",
    ),
    _target_case(
        "target-urdf-negative-mass",
        {"t.yaml": FD + "urdf: arm.urdf\n", "arm.urdf": _urdf(r'<mass value="', '<mass value="-')},
        "arm.urdf",
        "<mass> value: negative",
    ),
    _target_case(
        "target-urdf-negative-inertia",
        {"t.yaml": FD + "urdf: arm.urdf\n", "arm.urdf": _urdf(r'izz="', 'izz="-')},
        "arm.urdf",
        "<inertia> izz: negative",
    ),
    _target_case(
        "target-canfd-5khz",
        {"t.yaml": "period_s: 0.0002\nbus: {interface: virtual, fd: true, data_bitrate: 5000000}\n"},
        "bus:",
        "above the 85% limit",
    ),
    _target_case(
        "target-classical-500hz",
        {"t.yaml": "period_s: 0.002\nbus: {interface: virtual}\n"},
        "classical CAN",
        "101.4% load",
    ),
    _target_case("target-empty", {"t.yaml": ""}, "empty file"),
    _target_case("target-binary", {"t.yaml": bytes(range(256))}, "not a UTF-8 text file"),
    _target_case("target-nan", {"t.yaml": FD + "period_s: .nan\n"}, "period_s: Input should be a finite number"),
    _target_case(
        "target-ipc-channel-is-a-file",
        {"t.yaml": "bus: {interface: ipc, channel: ./afile, fd: true, data_bitrate: 5000000}\n", "afile": "x"},
        "afile",
        "is not a directory",
    ),
    # inject (schema checked before the socket is even tried)
    (
        "inject-negative-inertia",
        [
            "target",
            "inject",
            "--socket",
            "{tmp}/none.sock",
            '{"kind": "payload", "mass_kg": 1, "inertia_kg_m2": [-1, 0, 0]}',
        ],
        {},
        ["inject: payload.inertia_kg_m2.0: Input should be greater than or equal to 0"],
    ),
    (
        "inject-infinite",
        ["target", "inject", "--socket", "{tmp}/none.sock", '{"kind": "encoder_noise", "position_rad": Infinity}'],
        {},
        ["inject: encoder_noise.position_rad: Input should be a finite number"],
    ),
    (
        "inject-no-target",
        ["target", "inject", "--socket", "{tmp}/none.sock", '{"kind": "status"}'],
        {},
        ["{tmp}/none.sock: cannot reach the target"],
    ),
    # bundles
    (
        "bundle-dir-without-manifest",
        LMPC,
        {"bundles/empty.txt": ""},
        ["bundle directory {tmp}/bundles: no bundle for law 'pd'"],
    ),
    _bundle_case("bundle-torque-edited", lambda m: m["limits"].__setitem__("torque_nm", [1.0] * 6), "limits.torque_nm"),
    _bundle_case("bundle-wrong-urdf-sha", lambda m: m["robot"].__setitem__("urdf_sha256", "0" * 64), "urdf_sha256"),
    # bundles from elsewhere (issue 20): names outside the bundle, an edited manifest, no trusted signature
    _bundle_case(
        "bundle-member-outside",
        lambda m: m["files"].__setitem__("../pd/policy.onnx", "0" * 64),
        "'../pd/policy.onnx' is not a plain file name inside the bundle",
    ),
    _bundle_case(
        "bundle-limits-widened",
        lambda m: m["limits"].__setitem__("position_rad", [100.0] * 6),
        "bundle_id: ",
    ),
    _runtime_case(
        "bundle-unsigned",
        r"  mode: lmpc",
        "  mode: lmpc\n  trusted_keys: [lab.pub]",
        "signatures: none by a trusted key",
        files={"lab.pub": LAB_PUBLIC_PEM},
        where=f"bundle {PD_BUNDLE}/manifest.json",
    ),
    _runtime_case(
        "bundle-trusted-key-not-a-key",
        r"  mode: lmpc",
        "  mode: lmpc\n  trusted_keys: [lab.pub]",
        "bundle.trusted_keys[0]",
        "not a PEM public key",
        files={"lab.pub": "not a key"},
    ),
    # telemetry (issue 20)
    _plot_case("plot-truncated", npz_files.truncated(), "not a telemetry record"),
    _plot_case("plot-mismatched", npz_files.mismatched(), "column 'q_ref' has shape (60, 3), 'q' (50, 3)"),
    _plot_case("plot-period-string", npz_files.period_string(), "field period_s: 'fast' is not a positive number"),
    _plot_case("plot-600-joints", npz_files.many_joints(), "column 'q': 600 joints (plot draws at most 32)"),
    _plot_case("plot-inflating", npz_files.inflating(), "1040 MiB uncompressed (limit 1024 MiB)"),
    _plot_case("plot-fifo", FIFO, "not a regular file"),
    ("telemetry-timeout-nan", ["telemetry", "query", "schema", "--timeout", "nan"], {}, ["--timeout", "nan"]),
    ("telemetry-timeout<0", ["telemetry", "watch", "--timeout", "-1"], {}, ["--timeout", "-1.0"]),
    ("telemetry-seconds-nan", ["telemetry", "record", "--out", "x.npz", "--seconds", "nan"], {}, ["--seconds", "nan"]),
    _telemetry_check_case(
        "telemetry-zenoh-config-0.0.0.0",
        "{enabled: true, zenoh_config: z.json5}",
        {"z.json5": '{ listen: { endpoints: ["tcp/0.0.0.0:7447"] } }'},
        "z.json5': listen/endpoints 'tcp/0.0.0.0:7447' is not loopback",
    ),
    _telemetry_check_case(
        "telemetry-zenoh-config-connect-remote",
        "{enabled: true, listen: [tcp/127.0.0.1:7447], zenoh_config: z.json5}",
        {"z.json5": '{ connect: { endpoints: ["tcp/192.0.2.7:7447"] } }'},
        "z.json5': connect/endpoints 'tcp/192.0.2.7:7447' is not loopback",
    ),
    _telemetry_check_case(
        "telemetry-zenoh-config-default-listen",
        "{enabled: true, zenoh_config: z.json5}",
        {"z.json5": "{ mode: 'peer' }"},
        "listen/endpoints 'tcp/[::]:0' (Zenoh's default: the file sets none) is not loopback",
    ),
    _telemetry_check_case(
        "telemetry-controls-unauthenticated",
        "{enabled: true, controls_enabled: true}",
        {},
        "controls_enabled: the stop/reset queryables need authenticated peers",
    ),
    # runtime configs (issue 20): non-finite or huge values, strict types, duplicate keys, wide limits
    _runtime_case("hb-timeout-inf", r"heartbeat_timeout_s: 1.0", "heartbeat_timeout_s: .inf", "heartbeat_timeout_s"),
    _runtime_case(
        "run-ipc-channel-is-a-file",
        r"channel: hil,",
        "channel: ./afile,",
        "bus.transport.channel",
        "is not a directory",
        files={"afile": "x"},
    ),
    _runtime_case(
        "hb-timeout-1e300", r"heartbeat_timeout_s: 1.0", "heartbeat_timeout_s: 1e300", "bus.heartbeat_timeout_s"
    ),
    _runtime_case(
        "state-change-inf", r"state_change_timeout_s: 5.0", "state_change_timeout_s: .inf", "state_change_timeout_s"
    ),
    _runtime_case(
        "sdo-timeout-1e300", r"sdo_timeout_s: 2.0", "sdo_timeout_s: 1e300", "bus.sdo_timeout_s", "less than or equal"
    ),
    _runtime_case("warmup-1e9", r"warmup_cycles: 200", "warmup_cycles: 1000000000", "loop.warmup_cycles"),
    _runtime_case("ramp-inf", r"ramp_s: 2.0", "ramp_s: .inf", "reference.ramp_s"),
    _runtime_case("ramp-1e9", r"ramp_s: 2.0", "ramp_s: 1e9", "reference.ramp_s", "less than or equal to 60"),
    _runtime_case(
        "duration-inf", r"  stats_interval_s: 1.0", "  stats_interval_s: 1.0\n  duration_s: .inf", "loop.duration_s"
    ),
    _runtime_case(
        "node-id-true", r"node_id: 1,", "node_id: true,", "bus.joints.0.node_id: expected a number, got True"
    ),
    _runtime_case("period-string", r"period_s: 0.001 ", "period_s: '0.001' ", "bus.period_s: expected a number"),
    _runtime_case("duplicate-key", r"^robot: ur5_paper", "robot: ur5_paper\nrobot: ur5_paper", "duplicate key 'robot'"),
    _runtime_case(
        "safety-wider-than-bundle",
        r"position_upper_rad: null",
        "position_upper_rad: [100, 100, 100, 100, 100, 100]",
        "safety.position_upper_rad[0]: 100 is beyond the bundle's limit 3.14159",
    ),
    _runtime_case(
        "velocity-wider-than-bundle",
        r"velocity_limit_rad_s: null",
        "velocity_limit_rad_s: [1e9, 1, 1, 1, 1, 1]",
        "safety.velocity_limit_rad_s[0]: 1e+09 is beyond the bundle's limit 2.54",
    ),
    _runtime_case(
        "condition-duration-1e8",
        r"conditions_file: null",
        "conditions_file: c.yaml",
        "duration_s: 1e+08 s is above the limit 3600 s",
        where="c.yaml",
        files={"c.yaml": f"conditions:\n  - name: C1\n    amplitude_rad: {SIX}\n    duration_s: 1.0e8\n"},
    ),
    # --record (checked before the run) and --record-cycles
    _record_case("record-dev-full", "/dev/full", {}, "--record /dev/full: unknown record format '(no suffix)'"),
    _record_case("record-directory", "{tmp}/d.npz", {"d.npz/x": ""}, "--record {tmp}/d.npz: a directory"),
    _record_case("record-no-suffix", "{tmp}/run", {}, "--record {tmp}/run: unknown record format '(no suffix)'"),
    _record_case("record-parent-is-a-file", "{tmp}/f/run.npz", {"f": "x"}, "--record {tmp}/f: a file is in the way"),
    (
        "record-cycles<0",
        ["run", "--config", "{tmp}/r.yaml", "--record", "{tmp}/r.npz", "--record-cycles", "-1"],
        {"r.yaml": RUNTIME_YAML},
        ["--record-cycles", "greater than or equal to 1"],
    ),
    (
        "record-cycles-1e12",
        ["run", "--config", "{tmp}/r.yaml", "--record", "{tmp}/r.npz", "--record-cycles", "1000000000000"],
        {"r.yaml": RUNTIME_YAML},
        ["--record-cycles", "less than or equal to 3600000"],
    ),
    # target configs: unbounded noise, a boolean node id
    _target_case(
        "target-encoder-noise-1e6", {"t.yaml": FD + "plant: {encoder_noise_rad: 1.0e6}\n"}, "plant.encoder_noise_rad"
    ),
    _target_case(
        "target-node-id-true", {"t.yaml": FD + "drives: {node_ids: [true, 2, 3, 4, 5, 6]}\n"}, "drives.node_ids"
    ),
    _target_case(
        "target-duplicate-key", {"t.yaml": FD + "period_s: 0.001\nperiod_s: 0.002\n"}, "duplicate key 'period_s'"
    ),
]


# ~80 installed-`hil` processes, three at a time: about a minute on a quiet 2-core machine, several under load.
@pytest.mark.timeout(900)
def test_every_bad_input_is_one_line_naming_file_and_field_exit_2(tmp_path: Path, hil_command: list[str]) -> None:
    with ThreadPoolExecutor(max_workers=3) as pool:
        results = list(pool.map(lambda case: _run_case(hil_command, case, tmp_path), CASES))
    failures = []
    for name, code, stderr, expected in results:
        lines = [line for line in stderr.splitlines() if line.strip()]
        problems = []
        if code != 2:
            problems.append(f"exit {code}")
        if len(lines) != 1:
            problems.append(f"{len(lines)} stderr lines")
        if "Traceback" in stderr:
            problems.append("traceback")
        missing = [e for e in expected if e not in stderr]
        if missing:
            problems.append(f"missing {missing}")
        if problems:
            failures.append(f"{name}: {', '.join(problems)}: {stderr.strip()[-400:]!r}")
    assert not failures, "\n".join(failures)
    assert len(results) == len(CASES) >= 30
