"""What an OPC UA client reading results costs the trigger path (docs/integration.md, "OPC UA").

``python -m bench.opcua_queries [--gap S] [--spacing S] [--blocks 3] [--triggers 40]``

Station 1 in-process on simulated cameras (the part at its reference pose; its OPC UA server in
its own child process), the PLC twin triggering over Modbus/TCP on loopback, and an asyncua
client in a process of its own calling GetResultListFiltered (100 results a call) back to back,
``--gap`` seconds apart, in alternating blocks: ``--triggers``
PLC triggers without the client, as many with it, ``--blocks`` times. The link's
``query_spacing_s`` is ``--spacing`` (the station file's default: 0.25). Prints the station's
processing time of the PLC triggers (the record's total, ms) per condition and the client's
call times.

Not part of ``make bench`` (a minute, and meant for comparing settings).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml
from asyncua import Client, ua

from drivers.cameras import RenderOptions
from drivers.links.opcua import MV_URI
from drivers.links.opcua.settings import hash_password
from drivers.links.process import ProcessLink
from server.loopback import move_part, running_station, trigger
from server.settings import Settings
from server.station.core import StationOptions

ROOT = Path(__file__).resolve().parents[1]


def _station_file(folder: Path, spacing_s: float) -> Path:
    data = yaml.safe_load((ROOT / "deploy" / "stations" / "station1.yaml").read_text())
    data["deadline_ms"] = 1000.0  # the shared machine's hiccups are not NOK results here
    data.setdefault("links", {})["opcua"] = {
        "port": 0, "security": ["None"], "pki_dir": str(folder / "pki"),
        "query_spacing_s": spacing_s,
        "users": {"mes": {"role": "operator", "password_hash": hash_password("pw", 10_000)}}}
    path = folder / "station1.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _summary(name: str, values: list[float]) -> str:
    v = sorted(values)
    return (f"{name}: n {len(v)}, median {statistics.median(v):.1f}, "
            f"p90 {v[int(0.9 * (len(v) - 1))]:.1f}, max {v[-1]:.1f}")


async def client(url: str, gap_s: float) -> None:
    """The reading client (``--client URL``, a process of its own, as a plant's client is):
    GetResultListFiltered back to back until stdin closes; prints "ready", then the call times
    (ms) as one JSON list."""
    client = Client(url, timeout=30)
    client.set_user("mes")
    client.set_password("pw")
    await client.connect()
    await client.load_data_type_definitions()
    mv = await client.get_namespace_index(MV_URI)
    res = await client.nodes.objects.get_child([f"{mv}:VisionSystem", f"{mv}:ResultManagement"])
    mvt: Any = ua  # the Machine Vision types exist once load_data_type_definitions made them
    empty: list[Any] = [
        mvt.MeasIdDataType(Id=""), mvt.PartIdDataType(Id=""),
        mvt.RecipeIdExternalDataType(Id=""), mvt.RecipeIdInternalDataType(Id=""),
        mvt.ConfigurationIdDataType(Id=""), mvt.ConfigurationIdDataType(Id=""),
        mvt.ProductIdDataType(Id=""), mvt.JobIdDataType(Id="")]
    stop = asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
    calls: list[float] = []
    print("ready", flush=True)
    while not stop.done():
        t = time.perf_counter()
        await res.call_method(
            f"{mv}:GetResultListFiltered", ua.Variant(0, ua.VariantType.Int32),
            *empty, ua.Variant(100, ua.VariantType.UInt32),
            ua.Variant(0, ua.VariantType.UInt32), ua.Variant(0, ua.VariantType.Int32))
        calls.append((time.perf_counter() - t) * 1e3)
        await asyncio.sleep(gap_s)
    await client.disconnect()
    print(json.dumps(calls), flush=True)


async def run(gap_s: float, spacing_s: float, blocks: int, per_block: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        settings = Settings(station=_station_file(folder, spacing_s), data_dir=folder / "var")
        options = StationOptions(sim_render=RenderOptions(noise_sigma=0.0, shot_noise_gain=0.0,
                                                          supersample=4))
        async with running_station(settings, options, http_port=None) as lb:
            station = lb.runtime
            link = next(lk for lk in station.links
                        if isinstance(lk, ProcessLink) and lk.name == "opcua")
            await asyncio.to_thread(link.started.wait, 120)
            assert station.active is not None
            recipe = station.active.config
            await move_part(station, lb.twin, recipe.T_rf_from_pf0.matrix)
            url = f"opc.tcp://127.0.0.1:{link.port}/mvpose"
            calls: list[float] = []
            trigger_id = 1
            for _ in range(150):  # records for the client to page through, and a warm station
                await trigger(lb.twin, recipe, trigger_id, None)
                trigger_id += 1
            ms: dict[str, list[float]] = {"alone": [], "with the client": []}
            for _ in range(blocks):
                for cond in ms:
                    reader = None
                    if cond != "alone":
                        reader = subprocess.Popen(  # noqa: S603 - this module, our interpreter
                            [sys.executable, "-m", "bench.opcua_queries", "--client", url,
                             "--gap", str(gap_s)], cwd=ROOT, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
                        assert reader.stdout is not None
                        line = await asyncio.to_thread(reader.stdout.readline)
                        assert line.strip() == "ready", line
                    for _ in range(per_block):
                        status, _ = await trigger(lb.twin, recipe, trigger_id, None)
                        ms[cond].append(status.processing_ms)
                        trigger_id += 1
                    if reader is not None:
                        out, _ = await asyncio.to_thread(reader.communicate, "", 60)
                        calls += json.loads(out.strip().splitlines()[-1])
    print(f"query_spacing_s {spacing_s}, client gap {gap_s} s")
    for cond, values in ms.items():
        print(_summary(f"PLC trigger, station ms, {cond}", values))
    print(_summary("GetResultListFiltered (100 results), client ms", calls))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gap", type=float, default=0.0)
    parser.add_argument("--spacing", type=float, default=0.25)
    parser.add_argument("--blocks", type=int, default=3)
    parser.add_argument("--triggers", type=int, default=40)
    parser.add_argument("--client", metavar="URL", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.client:
        asyncio.run(client(args.client, args.gap))
    else:
        asyncio.run(run(args.gap, args.spacing, args.blocks, args.triggers))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
