#!/usr/bin/env python3
"""Check docker/compose.yaml without Docker: the YAML parses, and every `ros2 run` service's parameters exist.

Run after ``source scripts/env.sh``:  ``python docker/check_compose.py [--compose docker/compose.yaml]``.

For each service whose command is ``ros2 run <pkg> <exe> --ros-args ...``: the installed executable of the
colcon workspace (ros2_ws/install/<pkg>/lib/<pkg>/<exe>; the ros2 CLI is not needed) is started alone in a
private ROS domain with the same arguments, the image's paths mapped to this checkout (/ws/<pkg>/config ->
<repo>/<pkg>/config, /ws/runs -> a temporary folder) and compose's ``${VAR:-default}`` replaced by the
default. A probe node then asks the running node, over its parameter services, for the names it declared and
their values: every ``-p`` override and every key of the ``--params-file`` must be a declared parameter and
have the given value. The node is then stopped with SIGINT. Services that are not ``ros2 run`` (the replay
profile's ``ros2 bag play``) are listed as not checked. Exit code 1 when a check fails.
"""

from __future__ import annotations

import argparse
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
INSTALL = ROOT / "ros2_ws" / "install"
START_TIMEOUT_S = 60.0  # [s] for the node's parameter services to appear
CALL_TIMEOUT_S = 60.0  # [s] for an answer (a node busy warming up answers late)


def interpolate(text: str) -> str:
    """compose's interpolation with every variable unset: ${VAR:-default} -> default, $$ -> $."""
    text = re.sub(r"\$\{[A-Za-z_][A-Za-z0-9_]*:-([^}]*)\}", r"\1", text)
    return text.replace("$$", "$")


def overrides(args: list[str]) -> tuple[dict[str, object], list[Path]]:
    """The -p name:=value pairs (values parsed as ROS parses them: YAML) and the --params-file paths."""
    params: dict[str, object] = {}
    files: list[Path] = []
    for flag, value in zip(args, args[1:]):
        if flag == "-p":
            name, _, text = value.partition(":=")
            params[name] = yaml.safe_load(text)
        elif flag == "--params-file":
            files.append(Path(value))
    return params, files


def file_parameters(path: Path, node: str) -> dict[str, object]:
    """The node's parameters in a ROS parameter file, nested mappings flattened to dotted names as ROS does."""
    document = yaml.safe_load(path.read_text()) or {}

    def flatten(mapping: dict, prefix: str = "") -> dict[str, object]:
        out: dict[str, object] = {}
        for key, value in mapping.items():
            if isinstance(value, dict):
                out.update(flatten(value, f"{prefix}{key}."))
            else:
                out[f"{prefix}{key}"] = value
        return out

    for key in (node, f"/{node}", "/**"):
        if key in document:
            return flatten(document[key].get("ros__parameters", {}))
    return {}


def query(node_name: str, names: list[str], domain_timeout_s: float) -> tuple[set[str], dict[str, object]]:
    """Declared parameter names of ``node_name`` and the values of ``names`` (rclpy parameter services)."""
    import rclpy
    from rcl_interfaces.srv import GetParameters, ListParameters
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import parameter_value_to_python

    context = rclpy.context.Context()
    rclpy.init(context=context)
    probe = rclpy.create_node("tal_compose_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(probe)
    try:
        listing = probe.create_client(ListParameters, f"/{node_name}/list_parameters")
        getting = probe.create_client(GetParameters, f"/{node_name}/get_parameters")
        if not (listing.wait_for_service(timeout_sec=domain_timeout_s) and getting.wait_for_service(timeout_sec=5.0)):
            raise RuntimeError(f"{node_name}: no parameter services after {domain_timeout_s:.0f} s")

        def call(client, request):
            future = client.call_async(request)
            executor.spin_until_future_complete(future, timeout_sec=CALL_TIMEOUT_S)
            if future.result() is None:
                raise RuntimeError(f"{node_name}: {client.srv_name} did not answer")
            return future.result()

        declared = set(call(listing, ListParameters.Request()).result.names)
        present = [n for n in names if n in declared]
        values = call(getting, GetParameters.Request(names=present)).values
        return declared, {n: parameter_value_to_python(v) for n, v in zip(present, values)}
    finally:
        executor.shutdown()
        probe.destroy_node()
        rclpy.shutdown(context=context)


def same(expected: object, actual: object) -> bool:
    if isinstance(expected, (list, tuple)) and isinstance(actual, (list, tuple)):
        return len(expected) == len(actual) and all(same(e, a) for e, a in zip(expected, actual))
    if isinstance(expected, (int, float)) and isinstance(actual, (int, float)) and not isinstance(expected, bool):
        return float(expected) == float(actual)
    return expected == actual


def check_service(name: str, command: list[str], runs: Path, env: dict[str, str]) -> list[str]:
    """Problems found with one `ros2 run` service (empty: fine)."""
    pkg, exe, args = command[2], command[3], [interpolate(a) for a in command[4:]]
    args = [a.replace("/ws/runs", str(runs)).replace("/ws/", f"{ROOT}/") for a in args]
    binary = INSTALL / pkg / "lib" / pkg / exe
    if not binary.exists():
        return [f"no installed executable {binary}"]
    params, files = overrides(args)
    expected = {}
    for path in files:
        if not path.is_file():
            return [f"--params-file {path} does not exist"]
        expected.update(file_parameters(path, exe))
    expected.update(params)
    log = runs / f"{name}.log"
    with open(log, "w") as out:
        process = subprocess.Popen([str(binary), *args], env=env, stdout=out, stderr=subprocess.STDOUT,
                                   stdin=subprocess.DEVNULL, cwd=runs)  # fmt: skip
    problems: list[str] = []
    try:
        declared, values = query(exe, list(expected), START_TIMEOUT_S)
        for key, value in expected.items():
            if key not in declared:
                problems.append(f"parameter '{key}' is not declared by {exe}")
            elif not same(value, values[key]):
                problems.append(f"parameter '{key}': given {value!r}, the node has {values[key]!r}")
    except RuntimeError as exc:
        problems.append(f"{exc}; log: {log.read_text()[-1500:]}")
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
        try:
            code = process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            code = process.wait()
    if code not in (0, -signal.SIGINT):
        problems.append(f"exited with code {code}; log: {log.read_text()[-1500:]}")
    print(f"{name}: {len(expected)} parameters ({len(params)} -p, {len(expected) - len(params)} from files), "
          f"exit code {code}: {'ok' if not problems else 'FAILED'}", flush=True)  # fmt: skip
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--compose", type=Path, default=ROOT / "docker" / "compose.yaml")
    parser.add_argument("services", nargs="*", help="only these services (default: all)")
    args = parser.parse_args(argv)
    compose = yaml.safe_load(args.compose.read_text())
    print(f"{args.compose}: YAML parses; services: {', '.join(compose['services'])}")
    os.environ["ROS_DOMAIN_ID"] = str(random.randint(100, 140))  # a private domain for the nodes and the probe
    env = dict(os.environ)
    failed = 0
    with tempfile.TemporaryDirectory(prefix="tal_compose_") as tmp:
        for name, service in compose["services"].items():
            if args.services and name not in args.services:
                continue
            command = service.get("command", [])
            if command[:2] != ["ros2", "run"]:
                print(f"{name}: not a `ros2 run` service, not checked: {' '.join(command)[:120]}")
                continue
            problems = check_service(name, command, Path(tmp), env)
            for problem in problems:
                print(f"  {name}: {problem}")
            failed += bool(problems)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
