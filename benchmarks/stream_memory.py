"""Long logs: the streaming fixed-lag run's memory and speed, and the batch smoother's growth.

Usage::

    python benchmarks/stream_memory.py [--minutes 60] [--rate 200] [--batch 5,10,20,40,80] [--quick]

Prints JSON to stdout and writes ``benchmarks/results/stream_memory.json``.

The long log is a raw robot bag (MCAP) made from the real iCub CoM-sinusoid recording
(``icub-com-sinusoid-20s.bag``, beside the checkout): its messages played forwards then backwards
(a continuous motion: positions mirrored in time, joint velocities and angular rates negated,
specific forces and wrenches kept), over and over for ``--minutes``, resampled to ``--rate`` Hz.
It is written message by message, then run through the command line as a user would::

    flexforce run LONG.mcap --robot icub-identified --estimator fixed-lag -o OUT.csv [--no-cov]

in a child process whose memory is sampled every second: the proportional set size (PSS) of the
command and of its own child (the import runs in a forked process; PSS shares their common pages
between them, so the sum is what the run takes) -- the peak, and the memory at each tenth of the
run (flat = bounded) -- and the command's resident set (RSS, shared pages counted in full).  The
throughput and update times are the command's own report.  The batch smoother is timed on the
first 5, 10, 20, 40, 80 s of the same log (imported offline), each in a fresh process (peak RSS
from ``ru_maxrss``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
SOURCE = HERE.parents[1] / "shared" / "data" / "icub" / "icub-com-sinusoid-20s.bag"
ROBOT = "icub-identified"


def _read_source(path: Path) -> dict:
    """Per topic: (t in s from the first message, values (M, k), extra) of the source bag."""
    from rosbags.highlevel import AnyReader

    out: dict = {}
    with AnyReader([path]) as reader:
        t0 = None
        for conn, t, raw in reader.messages():
            msg: Any = reader.deserialize(raw, conn.msgtype)
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec or t
            t0 = stamp if t0 is None else min(t0, stamp)
            if conn.msgtype == "sensor_msgs/msg/Imu":
                v = [msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z,
                     msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z]
                extra = msg.header.frame_id
            elif conn.msgtype == "sensor_msgs/msg/JointState":
                v = list(msg.position) + list(msg.velocity)
                extra = list(msg.name)
            elif conn.msgtype == "geometry_msgs/msg/WrenchStamped":
                w = msg.wrench
                v = [w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z]
                extra = msg.header.frame_id
            else:
                continue
            out.setdefault(conn.topic, [conn.msgtype, [], [], extra])
            out[conn.topic][1].append(stamp)
            out[conn.topic][2].append(v)
    for topic, (msgtype, t, v, extra) in out.items():
        out[topic] = (msgtype, (np.array(t) - t0) * 1e-9, np.array(v), extra)
    return out


def _pingpong(t: np.ndarray, v: np.ndarray, sign: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Values at ``grid`` (s) of the signal played forwards then backwards, repeated; ``sign``
    (k,) multiplies the values played backwards (-1 for rates)."""
    T = t[-1]
    phase = np.mod(grid, 2 * T)
    back = phase > T
    s = np.where(back, 2 * T - phase, phase)
    out = np.empty((len(grid), v.shape[1]))
    for j in range(v.shape[1]):
        out[:, j] = np.interp(s, t, v[:, j])
    out[back] *= sign
    return out


def make_long_bag(out: Path, seconds: float, rate: float, source: Path = SOURCE) -> Path:
    """Write the long raw bag (module docstring) at ``out``; returns its path."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    src = _read_source(source)
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    t0_ns = 1_700_000_000_000_000_000
    period = 1.0 / rate
    n = int(seconds * rate)

    def header(t_ns, frame):
        sec, ns = divmod(int(t_ns), 1_000_000_000)
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns), frame_id=frame)

    def vec(a):
        return T["geometry_msgs/msg/Vector3"](x=float(a[0]), y=float(a[1]), z=float(a[2]))

    z9 = np.zeros(9)
    o9 = np.zeros(9)
    o9[0] = -1.0
    with Writer(out, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {topic: writer.add_connection(topic, msgtype, typestore=ts) for topic, (msgtype, *_) in src.items()}
        block = int(10 * rate)
        for a in range(0, n, block):
            grid = (np.arange(a, min(a + block, n))) * period
            series = {}
            for topic, (msgtype, t, v, extra) in src.items():
                sign = np.ones(v.shape[1])
                if msgtype == "sensor_msgs/msg/Imu":
                    sign[:3] = -1.0
                elif msgtype == "sensor_msgs/msg/JointState":
                    sign[len(extra):] = -1.0
                series[topic] = _pingpong(t, v, sign, grid)
            for k, g in enumerate(grid):
                t_ns = t0_ns + int(round(g * 1e9))
                for topic, (msgtype, _, _, extra) in src.items():
                    v = series[topic][k]
                    if msgtype == "sensor_msgs/msg/Imu":
                        msg = T[msgtype](header=header(t_ns, extra), orientation=T["geometry_msgs/msg/Quaternion"](
                            x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=o9, angular_velocity=vec(v[:3]),
                            angular_velocity_covariance=z9, linear_acceleration=vec(v[3:]),
                            linear_acceleration_covariance=z9)
                    elif msgtype == "sensor_msgs/msg/JointState":
                        nj = len(extra)
                        msg = T[msgtype](header=header(t_ns, ""), name=extra, position=np.ascontiguousarray(v[:nj]),
                                         velocity=np.ascontiguousarray(v[nj:]), effort=np.zeros(0))
                    else:
                        msg = T[msgtype](header=header(t_ns, extra), wrench=T["geometry_msgs/msg/Wrench"](
                            force=vec(v[:3]), torque=vec(v[3:])))
                    writer.write(conns[topic], t_ns, ts.serialize_cdr(msg, msgtype))
    return out


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return out


def _memory_mb(pid: int) -> tuple[float, float] | None:
    """(PSS of the process and its children, RSS of the process), MB.  PSS counts a page shared by
    n processes (the import's child is forked: the libraries' pages are shared) as 1/n in each, so
    the sum is the memory the run takes; RSS counts shared pages in full in every process."""
    total, rss = 0.0, None
    for p in [pid] + _children(pid):
        try:
            text = Path(f"/proc/{p}/smaps_rollup").read_text()
        except OSError:
            continue
        pss = re.search(r"^Pss:\s+(\d+) kB", text, re.M)
        total += int(pss[1]) / 1024.0 if pss else 0.0
        if p == pid:
            found = re.search(r"^Rss:\s+(\d+) kB", text, re.M)
            rss = int(found[1]) / 1024.0 if found else None
    return (total, rss) if rss is not None else None


def stream_run(bag: Path, out: Path, no_cov: bool, block: int = 1) -> dict:
    """The command-line streaming run in a child process, its RSS sampled every second; ``block``
    samples per update (``--block``)."""
    cmd = [sys.executable, "-m", "flexforce.cli", "run", str(bag), "--robot", ROBOT, "--estimator", "fixed-lag",
           "-o", str(out), "-q", "--force"] + (["--no-cov"] if no_cov else []) + \
        (["--block", str(block)] if block != 1 else [])
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    samples = []
    while proc.poll() is None:
        mem = _memory_mb(proc.pid)
        if mem is not None:
            samples.append((time.perf_counter() - t0, *mem))
        time.sleep(1.0)
    stdout, stderr = proc.communicate()
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {stderr.strip()}")
    found = re.search(r"(\d+) steps streamed in ([\d.]+) s \(([\d.]+)x real time\), update ([\d.]+) ms median, "
                      r"([\d.]+) ms p99", stdout)
    per_sample = re.search(r"([\d.]+) ms per sample", stdout)
    curve = np.array([m for _, m, _ in samples]) if samples else np.zeros(1)
    rss = np.array([r for _, _, r in samples]) if samples else np.zeros(1)
    tenths = [float(curve[min(len(curve) - 1, int(f * len(curve)))]) for f in np.linspace(0.1, 1.0, 10)]
    return {"command": " ".join(cmd[2:]), "wall_s": wall, "peak_pss_mb": float(curve.max()),
            "pss_at_tenths_mb": tenths, "pss_growth_second_half_mb": float(tenths[-1] - tenths[4]),
            "peak_rss_main_process_mb": float(rss.max()),
            "steps": int(found[1]) if found else None, "stream_wall_s": float(found[2]) if found else None,
            "realtime_factor": float(found[3]) if found else None,
            "update_median_ms": float(found[4]) if found else None,
            "update_p99_ms": float(found[5]) if found else None,
            "samples_per_update": block,
            "update_per_sample_ms": float(per_sample[1]) if per_sample else (float(found[4]) if found and block == 1
                                                                             else None),
            "loadavg_at_start": load0, "loadavg_at_end": os.getloadavg(), "stdout": stdout.strip()}


BATCH_CHILD = """
import json, resource, sys, time
from flexforce.datasets.io.rosimport import import_bag
from flexforce.datasets.robot import RobotConfig
from flexforce.factors.model import ModelConfig
from flexforce.smoother import run_batch
rec = import_bag(sys.argv[1], sys.argv[2]).window(0.0, float(sys.argv[3]))
model = ModelConfig.from_recording(rec, robot=RobotConfig.load(sys.argv[2]))
t0 = time.perf_counter()
est = run_batch(rec, model)
wall = time.perf_counter() - t0
print(json.dumps({"seconds": float(sys.argv[3]), "steps": rec.n, "batch_s": wall,
                  "iterations": est.meta.get("iterations"),
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}))
"""


def batch_growth(folder: Path, rate: float, lengths: list[float]) -> dict:
    """The batch smoother on logs of each length (each its own bag, imported whole: the import's
    memory is that of the log, not of an hour)."""
    rows = []
    for s in lengths:
        bag = folder / f"batch-{s:g}s.mcap"
        make_long_bag(bag, s + 0.5, rate)  # the window below keeps the first s seconds
        res = subprocess.run([sys.executable, "-c", BATCH_CHILD, str(bag), ROBOT, str(s)], capture_output=True,
                             text=True, check=False)
        if res.returncode != 0:
            raise RuntimeError(f"batch on {s} s failed: {res.stderr.strip()[-400:]}")
        rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
    x = np.log([r["steps"] for r in rows])
    slope_t = float(np.polyfit(x, np.log([r["batch_s"] for r in rows]), 1)[0]) if len(rows) > 1 else None
    mem = [r["peak_rss_mb"] for r in rows]
    slope_m = (float(np.polyfit([r["seconds"] for r in rows], mem, 1)[0]) if len(rows) > 1 else None)
    return {"runs": rows, "time_exponent": slope_t, "memory_mb_per_s": slope_m}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=60.0, help="length of the long log (min)")
    parser.add_argument("--rate", type=float, default=200.0, help="message rate of the long log (Hz)")
    parser.add_argument("--no-cov-minutes", type=float, default=10.0,
                        help="the run without covariances on the first this many minutes (default 10)")
    parser.add_argument("--batch", default="5,10,20,40,80", help="batch lengths, s (comma-separated; '' for none)")
    parser.add_argument("--quick", action="store_true", help="2 minutes, batch 5,10 s")
    parser.add_argument("--blocks", default="1,10",
                        help="samples per update of the runs with covariances (comma-separated; the run without "
                             "covariances takes the last)")
    parser.add_argument("--keep", type=Path, help="keep the long bag at this path (reused when it exists)")
    parser.add_argument("--batch-only", action="store_true",
                        help="only the batch runs, replacing them in the committed JSON")
    args = parser.parse_args(argv)
    out = HERE / "results" / "stream_memory.json"
    if args.batch_only:
        lengths = [float(x) for x in args.batch.split(",") if x.strip()]
        result: dict = json.loads(out.read_text())
        with tempfile.TemporaryDirectory() as tmp:
            result["batch"] = batch_growth(Path(tmp), args.rate, lengths)
        out.write_text(json.dumps(result, indent=2) + "\n")
        print(json.dumps(result["batch"], indent=2))
        return result
    if args.quick:
        args.minutes, args.batch = 2.0, "5,10"
    if not SOURCE.exists():
        raise SystemExit(f"{SOURCE} not found: the iCub recordings must be beside the checkout")
    with tempfile.TemporaryDirectory() as tmp:
        bag = args.keep or Path(tmp) / "long.mcap"
        t0 = time.perf_counter()
        if not bag.exists():
            make_long_bag(bag, args.minutes * 60.0, args.rate)
        made = time.perf_counter() - t0
        size = sum(f.stat().st_size for f in bag.rglob("*") if f.is_file()) if bag.is_dir() else bag.stat().st_size
        result = {
            "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
            "log": {"minutes": args.minutes, "rate_hz": args.rate, "source": SOURCE.name, "bag_mb": size / 2**20,
                    "write_s": made},
            "stream": {},
        }
        blocks = [int(b) for b in args.blocks.split(",") if b.strip()] or [1]
        for b in blocks:
            key = "with_covariance" if b == 1 else f"with_covariance_block{b}"
            result["stream"][key] = stream_run(bag, Path(tmp) / "cov.csv", no_cov=False, block=b)
        short = bag
        if args.no_cov_minutes < args.minutes:
            short = Path(tmp) / "short.mcap"
            make_long_bag(short, args.no_cov_minutes * 60.0, args.rate)
        result["stream"]["without_covariance"] = stream_run(short, Path(tmp) / "nocov.csv", no_cov=True,
                                                            block=blocks[-1])
        result["stream"]["without_covariance"]["minutes"] = min(args.no_cov_minutes, args.minutes)
        result["load"] = {"loadavg_at_end": os.getloadavg()}
        lengths = [float(x) for x in args.batch.split(",") if x.strip()]
        if lengths:
            result["batch"] = batch_growth(Path(tmp), args.rate, lengths)
    if not args.quick:
        out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
