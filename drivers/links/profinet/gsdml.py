"""The device's GSDML (GSDML V2.4), generated from the module table (:mod:`.modules`), which
takes its bytes from the fieldbus layout: ``python -m drivers.links.profinet.gsdml`` writes the
shipped file next to this module; tests/drivers/test_profinet_core.py checks that it is current.
An integrator with a vendor id of their own regenerates it with ``--vendor-id``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Final
from xml.sax.saxutils import quoteattr

from .. import layout
from . import im
from . import modules as mod
from .settings import UNASSIGNED_VENDOR

DATE: Final = "20261127"  # the GSDML's release date: change it with the module table
FILENAME: Final = f"GSDML-V2.4-mvpose-station-{DATE}.xml"
SHIPPED: Final = Path(__file__).with_name(FILENAME)
_TYPES: Final = {"WORD": "Unsigned16", "UINT": "Unsigned16", "UDINT": "Unsigned32",
                 "DINT": "Integer32", "REAL": "Float32"}


def _items(fields: list[layout.Field], texts: dict[str, str], prefix: str) -> list[str]:
    out = []
    for f in fields:
        tid = f"IDT_{prefix}_{f.name.upper()}"
        texts[tid] = f"{f.name} ({f.unit})" if f.unit else f.name
        if f.type == "CHAR":
            out.append(f'<DataItem DataType="OctetString" Length="{f.count}" TextId="{tid}"/>')
        else:
            out += [f'<DataItem DataType="{_TYPES[f.type]}" TextId="{tid}"/>'] * f.count
    return out


def _io(sub: mod.Submodule, texts: dict[str, str]) -> str:
    parts = []
    if sub.input_length:
        items = _items(mod.input_fields(sub), texts, "IN")
        parts.append('<Input Consistency="All items consistency">' + "".join(items) + "</Input>")
    if sub.output_length:
        items = _items(mod.output_fields(sub), texts, "OUT")
        parts.append('<Output Consistency="All items consistency">' + "".join(items)
                     + "</Output>")
    return "<IOData>" + "".join(parts) + "</IOData>"


def render(vendor_id: int = UNASSIGNED_VENDOR, device_id: int = 0x0001) -> str:
    texts: dict[str, str] = {
        "IDT_INFO_DEVICE": "mvpose station: part pose for the robot frame offset",
        "IDT_DAP": "mvpose station", "IDT_INTERFACE": "X1", "IDT_PORT": "X1 P1"}
    user = [s for s in mod.SUBMODULES if s.slot > 0]
    modules = []
    for s in user:
        tid = f"IDT_MOD_{s.name.upper().replace(' ', '_')}"
        texts[tid] = s.name
        modules.append(
            f'<ModuleItem ID="IDM_{s.slot}" ModuleIdentNumber="0x{s.module_ident:08X}">'
            f'<ModuleInfo><Name TextId="{tid}"/><InfoText TextId="{tid}"/></ModuleInfo>'
            f'<VirtualSubmoduleList><VirtualSubmoduleItem ID="IDS_{s.slot}" '
            f'SubmoduleIdentNumber="0x{s.submodule_ident:08X}" MayIssueProcessAlarm="false">'
            f'{_io(s, texts)}<ModuleInfo><Name TextId="{tid}"/></ModuleInfo>'
            f"</VirtualSubmoduleItem></VirtualSubmoduleList></ModuleItem>")
    refs = "".join(f'<ModuleItemRef ModuleItemTarget="IDM_{s.slot}" AllowedInSlots="{s.slot}" '
                   f'FixedInSlots="{s.slot}"/>' for s in user)
    n_in = sum(s.input_length + 1 for s in mod.SUBMODULES) + len(mod.SUBMODULES)
    n_out = sum(s.output_length + 1 for s in mod.SUBMODULES) + len(mod.SUBMODULES)
    text_list = "".join(f"<Text TextId={quoteattr(k)} Value={quoteattr(v)}/>"
                        for k, v in sorted(texts.items()))
    body = f"""<?xml version="1.0" encoding="UTF-8"?>
<ISO15745Profile xmlns="http://www.profibus.com/GSDML/2003/11/DeviceProfile" \
xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" \
xsi:schemaLocation="http://www.profibus.com/GSDML/2003/11/DeviceProfile \
..\\xsd\\GSDML-DeviceProfile-V2.4.xsd">
<!-- generated from drivers/links/layout.py by `python -m drivers.links.profinet.gsdml` -->
<ProfileHeader>
<ProfileIdentification>PROFINET Device Profile</ProfileIdentification>
<ProfileRevision>1.00</ProfileRevision>
<ProfileName>Device Profile for PROFINET Devices</ProfileName>
<ProfileSource>PROFIBUS Nutzerorganisation e. V. (PNO)</ProfileSource>
<ProfileClassID>Device</ProfileClassID>
<ISO15745Reference><ISO15745Part>4</ISO15745Part><ISO15745Edition>1</ISO15745Edition>\
<ProfileTechnology>GSDML</ProfileTechnology></ISO15745Reference>
</ProfileHeader>
<ProfileBody>
<DeviceIdentity VendorID="0x{vendor_id:04X}" DeviceID="0x{device_id:04X}">\
<InfoText TextId="IDT_INFO_DEVICE"/><VendorName Value="mvpose"/></DeviceIdentity>
<DeviceFunction><Family MainFamily="General" ProductFamily="mvpose"/></DeviceFunction>
<ApplicationProcess>
<DeviceAccessPointList>
<DeviceAccessPointItem ID="DAP1" PhysicalSlots="0..{max(s.slot for s in user)}" \
ModuleIdentNumber="0x{mod.DAP.module_ident:08X}" MinDeviceInterval="32" \
DNS_CompatibleName="mvpose-station" FixedInSlots="0" ObjectUUID_LocalIndex="1" \
RequiredSchemaVersion="V2.4" DeviceAccessSupported="false" MultipleWriteSupported="false" \
CheckDeviceID_Allowed="true" NameOfStationNotTransferable="false" LLDP_NoD_Supported="true" \
ResetToFactoryModes="2">
<ModuleInfo><Name TextId="IDT_DAP"/><InfoText TextId="IDT_INFO_DEVICE"/>\
<VendorName Value="mvpose"/><OrderNumber Value="MVPOSE-PN"/><HardwareRelease Value="1"/>\
<SoftwareRelease Value="V1.0.0"/></ModuleInfo>
<CertificationInfo ConformanceClass="A" ApplicationClass="" NetloadClass="I"/>
<IOConfigData MaxInputLength="{n_in}" MaxOutputLength="{n_out}"/>
<UseableModules>{refs}</UseableModules>
<VirtualSubmoduleList><VirtualSubmoduleItem ID="IDS_DAP" \
SubmoduleIdentNumber="0x{mod.DAP.submodule_ident:08X}" MayIssueProcessAlarm="false" \
Writeable_IM_Records="{' '.join(str(r.number) for r in im.RECORDS.values())}">\
<IOData/><ModuleInfo><Name TextId="IDT_DAP"/></ModuleInfo></VirtualSubmoduleItem>\
</VirtualSubmoduleList>
<SystemDefinedSubmoduleList>
<InterfaceSubmoduleItem ID="IDS_I" SubslotNumber="{mod.INTERFACE.subslot}" \
SubmoduleIdentNumber="0x{mod.INTERFACE.submodule_ident:08X}" TextId="IDT_INTERFACE" \
SupportedRT_Classes="RT_CLASS_1" SupportedProtocols="LLDP">\
<ApplicationRelations StartupMode="Advanced;Legacy"><TimingProperties SendClock="32" \
ReductionRatio="1 2 4 8 16 32 64 128 256 512"/></ApplicationRelations></InterfaceSubmoduleItem>
<PortSubmoduleItem ID="IDS_P1" SubslotNumber="{mod.PORT.subslot}" \
SubmoduleIdentNumber="0x{mod.PORT.submodule_ident:08X}" TextId="IDT_PORT" \
MaxPortRxDelay="350" MaxPortTxDelay="160"><MAUTypeList><MAUTypeItem Value="16"/>\
</MAUTypeList></PortSubmoduleItem>
</SystemDefinedSubmoduleList>
</DeviceAccessPointItem>
</DeviceAccessPointList>
<ModuleList>
{chr(10).join(modules)}
</ModuleList>
<ExternalTextList><PrimaryLanguage>{text_list}</PrimaryLanguage></ExternalTextList>
</ApplicationProcess>
</ProfileBody>
</ISO15745Profile>
"""
    return body


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--vendor-id", type=lambda v: int(v, 0), default=UNASSIGNED_VENDOR)
    parser.add_argument("--device-id", type=lambda v: int(v, 0), default=0x0001)
    parser.add_argument("--out", type=Path, default=SHIPPED)
    args = parser.parse_args()
    args.out.write_text(render(args.vendor_id, args.device_id), encoding="utf-8")
    print(args.out)


if __name__ == "__main__":
    main()
