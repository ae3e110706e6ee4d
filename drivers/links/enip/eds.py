"""The adapter's EDS (Electronic Data Sheet), generated from the fieldbus layout.

The shipped file ``mvpose.eds`` beside this module is this generator's output with the default
settings (a test keeps them equal); an integrator with their own vendor id or product code
writes their own with ``python -m drivers.links.enip.eds --vendor-id N > mvpose.eds``. Sections
and keywords follow the ODVA EDS specification (CIP Vol 1, chapter 7): [File], [Device],
[Device Classification], [Params], [Assembly], [Connection Manager], [Port], [Capacity].
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from .. import layout
from .codec import Identity
from .objects import Assemblies
from .settings import EnipLinkConfig

# CIP elementary data type codes (Vol 1, C-6.1) and sizes, by the layout's type names
TYPES = {"WORD": (0xD2, 2), "UINT": (0xC7, 2), "UDINT": (0xC8, 4), "DINT": (0xC4, 4),
         "REAL": (0xCA, 4), "CHAR": (0xC6, 1)}
CREATED = "11-27-2026"  # fixed, so the file is reproducible


def _params(fields: Sequence[layout.Field], first: int, direction: str) -> tuple[list[str],
                                                                                 list[str]]:
    """Params entries for ``fields`` (numbered from ``first``) and the assembly's member list."""
    params, members = [], []
    for n, f in enumerate(fields, start=first):
        code, size = TYPES[f.type]
        help_ = f.description.replace('"', "'")
        unit = (f.unit or "").replace('"', "'")
        params.append(
            f"        Param{n} =\n"
            f"                0,,,0x0010,             $ {direction} {f.name}: read-only\n"
            f"                0x{code:02X},{size},              $ data type, size\n"
            f'                "{f.name}","{unit}","{help_[:80]}",\n'
            "                ,,,\n"
            "                ,,,,\n"
            "                ,,,,\n"
            "                ;")
        members += [f"{size * 8},Param{n}"] * f.count
    return params, members


def _assembly(instance: int, name: str, size: int, members: list[str]) -> str:
    body = ",\n                ".join(members)
    tail = f",\n                {body}" if members else ""
    return (f"        Assem{instance} =\n"
            f'                "{name}",\n'
            f'                "20 04 24 {instance:02X} 30 03",\n'
            f"                {size},\n"
            "                0x0000,\n"
            f"                ,{tail};")


def eds_text(identity: Identity, assemblies: Assemblies | None = None) -> str:
    """The EDS for an adapter with ``identity`` and ``assemblies``, members from the layout."""
    a = assemblies or Assemblies()
    rpi = len(layout.INPUT_FIELDS) + len(layout.OUTPUT_FIELDS) + 1
    inputs, in_members = _params(layout.INPUT_FIELDS, 1, "input")
    outputs, out_members = _params(layout.OUTPUT_FIELDS, 1 + len(layout.INPUT_FIELDS), "output")
    rpi_param = (f"        Param{rpi} =\n"
                 "                0,,,0x0000,             $ RPI\n"
                 "                0xC8,4,                 $ UDINT\n"
                 '                "RPI","us","Requested packet interval",\n'
                 "                2000,10000000,4000,     $ min, max, default\n"
                 "                ,,,,\n"
                 "                ,,,,\n"
                 "                ;")
    path = (f"20 04 24 {a.config_instance:02X} 2C {a.output_instance:02X} "
            f"2C {a.input_instance:02X}")
    lines = [
        "$ EDS of the mvpose EtherNet/IP adapter, generated from drivers/links/layout.py by",
        "$ drivers/links/enip/eds.py: do not edit, regenerate.",
        "",
        "[File]",
        '        DescText = "mvpose station: EtherNet/IP adapter for the PLC handshake";',
        f"        CreateDate = {CREATED};",
        "        CreateTime = 00:00:00;",
        f"        Revision = {identity.revision[0]}.{identity.revision[1]};",
        "",
        "[Device]",
        f"        VendCode = {identity.vendor_id};",
        '        VendName = "mvpose";',
        f"        ProdType = {identity.device_type};",
        '        ProdTypeStr = "Generic Device";',
        f"        ProdCode = {identity.product_code};",
        f"        MajRev = {identity.revision[0]};",
        f"        MinRev = {identity.revision[1]};",
        f'        ProdName = "{identity.product_name}";',
        '        Catalog = "mvpose";',
        "",
        "[Device Classification]",
        "        Class1 = EtherNetIP;",
        "",
        "[Params]",
        *inputs, *outputs, rpi_param,
        "",
        "[Assembly]",
        '        Object_Name = "Assembly Object";',
        "        Object_Class_Code = 0x04;",
        _assembly(a.input_instance, "Input: status and result (T->O)", a.input_size,
                  in_members),
        _assembly(a.output_instance, "Output: control, trigger, robot pose (O->T)",
                  a.output_size, out_members),
        _assembly(a.config_instance, "Configuration (empty)", 0, []),
        "",
        "[Connection Manager]",
        '        Object_Name = "Connection Manager Object";',
        "        Object_Class_Code = 0x06;",
        "        Connection1 =",
        "                0x04030002,             $ class 1, cyclic or change of state, "
        "exclusive owner",
        "                0x44440405,             $ fixed sizes; O->T run/idle header, T->O "
        "modeless; point to point; scheduled",
        f"                Param{rpi},{a.output_size},Assem{a.output_instance},"
        "  $ O->T RPI, size, format",
        f"                Param{rpi},{a.input_size},Assem{a.input_instance},"
        " $ T->O RPI, size, format",
        "                ,,                      $ config part 1 (none)",
        f"                0,Assem{a.config_instance},"
        "            $ config part 2 (empty)",
        '                "Exclusive Owner",',
        '                "",',
        f'                "{path}";',
        "",
        "[Port]",
        '        Port1 = TCP, "EtherNet/IP", "20 F5 24 01", 2;',
        "",
        "[Capacity]",
        "        MaxIOConnections = 1;",
        "        MaxMsgConnections = 7;",
        # the larger connection's size with its 2-byte sequence count
        f"        TSpec1 = TxRx, {max(a.input_size, a.output_size) + 2}, 500;",
        "",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m drivers.links.enip.eds",
                                     description="Write the adapter's EDS to standard output.")
    parser.add_argument("--vendor-id", type=int, default=None)
    parser.add_argument("--product-code", type=int, default=None)
    args = parser.parse_args(argv)
    given = {k: v for k, v in (("vendor_id", args.vendor_id),
                               ("product_code", args.product_code)) if v is not None}
    cfg = EnipLinkConfig.model_validate(given)
    sys.stdout.write(eds_text(cfg.identity(), cfg.assemblies()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
