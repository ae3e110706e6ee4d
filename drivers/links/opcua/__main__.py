"""``python -m drivers.links.opcua``: what every start of the OPC UA link costs, in seconds."""

import asyncio
import logging

from drivers.links.opcua.nodesets import load_times

logging.basicConfig(level=logging.ERROR)
for name, seconds in asyncio.run(load_times()).items():
    print(f"{name}: {seconds:.2f} s")
