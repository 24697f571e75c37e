"""Write the SunSpec inverter twin (examples/sunspec-twin.toml) and the data files of the
quirks real devices show (tests/data/sunspec/), for `mbtool serve --data` (issue 34).

    python scripts/make_sunspec_twin.py            # write them
    python scripts/make_sunspec_twin.py --check    # exit 1 if a written file is not what this makes

The twin is a three-phase PV inverter with two MPPT inputs and a meter at the grid point:
common model 1, inverter 103, nameplate 120, settings 121, status 122, controls 123,
MPPT 160 with two modules and meter 203, from holding register 40000 ("SunS") to the end
model.  Each model is laid out by its SunSpec definition (mbtool/sunspec/models), every
point the twin does not name holding SunSpec's "not implemented" value for its type (pads
hold 0x8000), so the twin shows implemented and unimplemented points alike.
"""

from __future__ import annotations

import math
import struct
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from mbtool.codec.values import encode_values  # noqa: E402
from mbtool.sunspec.layout import lay_out  # noqa: E402
from mbtool.sunspec.models import END_MODEL, MARKER, TYPES, definition, point_size  # noqa: E402

BASE = 40000

# Raw values (before scale factors) by point name; a repeating group's by its repeats.
TWIN: list[tuple[int, dict]] = [
    (
        1,
        {
            "Mn": "mbtool",
            "Md": "SunSpec twin 10k",
            "Opt": "3ph 2MPPT",
            "Vr": "1.0.0",
            "SN": "TWIN-0001",
            "DA": 1,
        },
    ),
    (
        103,
        {
            "A": 1250,
            "AphA": 417,
            "AphB": 416,
            "AphC": 417,
            "A_SF": -2,
            "PPVphAB": 3998,
            "PPVphBC": 4003,
            "PPVphCA": 4001,
            "PhVphA": 2301,
            "PhVphB": 2299,
            "PhVphC": 2305,
            "V_SF": -1,
            "W": 8600,
            "W_SF": 0,
            "Hz": 5001,
            "Hz_SF": -2,
            "VA": 8650,
            "VA_SF": 0,
            # VAr and VAr_SF not implemented: a point and its scale factor alike.
            "PF": -985,
            "PF_SF": -1,
            "WH": 153427,
            "WH_SF": 2,
            "DCA": 2510,
            "DCA_SF": -2,
            "DCV": 3500,
            "DCV_SF": -1,
            "DCW": 8784,
            "DCW_SF": 0,
            "TmpCab": 452,
            "TmpSnk": 521,
            "Tmp_SF": -1,  # TmpTrns, TmpOt not implemented
            "St": 4,
            "Evt1": (1 << 3) | (1 << 7),
            "Evt2": 0,
        },
    ),
    (
        120,
        {
            "DERTyp": 4,
            "WRtg": 100,
            "WRtg_SF": 2,
            "VARtg": 100,
            "VARtg_SF": 2,
            "VArRtgQ1": 44,
            "VArRtgQ2": 44,
            "VArRtgQ3": -44,
            "VArRtgQ4": -44,
            "VArRtg_SF": 2,
            "ARtg": 1600,
            "ARtg_SF": -2,
            "PFRtgQ1": -80,
            "PFRtgQ2": -80,
            "PFRtgQ3": 80,
            "PFRtgQ4": 80,
            "PFRtg_SF": -2,
        },
    ),
    (
        121,
        {
            "WMax": 10000,
            "WMax_SF": 0,
            "VRef": 230,
            "VRef_SF": 0,
            "VRefOfs": 0,
            "VRefOfs_SF": 0,
            "VMax": 2530,
            "VMin": 1840,
            "VMinMax_SF": -1,
            "VAMax": 10000,
            "VAMax_SF": 0,
            "ECPNomHz": 5000,
            "ECPNomHz_SF": -2,
            "ConnPh": 7,
        },
    ),
    (
        122,
        {
            "PVConn": 0b111,
            "ECPConn": 0b10,
            "ActWh": 15342700,
            "WAval": 9800,
            "WAval_SF": 0,
            "StActCtl": 0b1,
            "TmSrc": "RTC",
            "Tms": 775_000_000,
            "RtSt": 0,
            "Ris": 1200,
            "Ris_SF": 0,
        },
    ),
    (
        123,
        {
            "Conn_WinTms": 0,
            "Conn_RvrtTms": 0,
            "Conn": 1,
            "WMaxLimPct": 1000,
            "WMaxLimPct_WinTms": 0,
            "WMaxLimPct_RvrtTms": 0,
            "WMaxLimPct_RmpTms": 10,
            "WMaxLim_Ena": 1,
            "OutPFSet": -1000,
            "OutPFSet_Ena": 0,
            "WMaxLimPct_SF": -1,
            "OutPFSet_SF": -3,
        },
    ),
    (
        160,
        {
            "DCA_SF": -2,
            "DCV_SF": -1,
            "DCW_SF": 0,
            "DCWH_SF": 2,
            "Evt": 0,
            "N": 2,
            "module": [
                {
                    "ID": 1,
                    "IDStr": "PV1 east",
                    "DCA": 1260,
                    "DCV": 3502,
                    "DCW": 4412,
                    "DCWH": 76500,
                    "Tms": 775_000_000,
                    "Tmp": 41,
                    "DCSt": 4,
                    "DCEvt": 0,
                },
                {
                    "ID": 2,
                    "IDStr": "PV2 west",
                    "DCA": 1250,
                    "DCV": 3498,
                    "DCW": 4372,
                    "DCWH": 76900,
                    "Tms": 775_000_000,
                    "Tmp": 39,
                    "DCSt": 4,
                    "DCEvt": 0,
                },
            ],
        },
    ),
    (
        203,
        {
            "A": 371,
            "AphA": 124,
            "AphB": 123,
            "AphC": 124,
            "A_SF": -1,
            "PhV": 2302,
            "PhVphA": 2301,
            "PhVphB": 2299,
            "PhVphC": 2305,
            "PPV": 3999,
            "PhVphAB": 3998,
            "PhVphBC": 4003,
            "PhVphCA": 4001,
            "V_SF": -1,
            "Hz": 5001,
            "Hz_SF": -2,
            "W": -2500,
            "WphA": -833,
            "WphB": -834,
            "WphC": -833,
            "W_SF": 0,
            "PF": -98,
            "PF_SF": -2,
            "TotWhExp": 823450,
            "TotWhImp": 412300,
            "TotWh_SF": 1,
            "Evt": 0,
        },
    ),
]


# Not in the twin: the tests' model of groups counted by points, one inside the other.
VOLT_VAR = {
    "Ena": 1,
    "NPt": 2,
    "NCrv": 2,
    "V_SF": -1,
    "DeptRef_SF": 0,
    "RspTms_SF": 0,
    "Crv": [
        {"ActPt": 2, "DeptRef": 1, "Pt": [{"V": 920, "Var": 300}, {"V": 1080, "Var": -300}]},
        {"ActPt": 2, "DeptRef": 1, "Pt": [{"V": 900, "Var": 200}, {"V": 1100, "Var": -200}]},
    ],
}


def model_registers(model_id: int, values: dict) -> list[int]:
    """The model's registers after its id and length, laid out by its definition."""
    group = definition(model_id)
    return _group(group, values, top=True)


def _group(group: dict, values: dict, top: bool = False) -> list[int]:
    out: list[int] = []
    for point in group.get("points", ()):
        name = point["name"]
        if top and name in ("ID", "L"):
            continue
        out += _point(point, values.get(name))
    for sub in group.get("groups", ()):
        repeats = values.get(sub["name"], [] if sub.get("count") is not None else {})
        for each in repeats if isinstance(repeats, list) else [repeats]:
            out += _group(sub, each)
    return out


def _point(point: dict, value) -> list[int]:
    kind = TYPES[point["type"]]
    size = point_size(point)
    if kind.name == "pad":
        return [0x8000]
    if value is None:  # not implemented: the value SunSpec gives the type
        if kind.map_type is None:
            return [0xFFFF] * size if kind.name == "eui48" else [0] * size
        value = kind.unimplemented[0]
        if isinstance(value, float) and math.isnan(value):
            return list(struct.unpack(f">{size}H", struct.pack(">f" if size == 2 else ">d", value)))
    if kind.map_type == "string":
        return (encode_values([value], "string") + [0] * size)[:size]
    return encode_values([value], kind.map_type)


def chain(models: list[tuple[int, dict]], end: list[int] | None = None) -> list[int]:
    """The registers from the base: the marker, each model's id, length and registers, the end."""
    out = list(MARKER)
    for model_id, values in models:
        registers = values if isinstance(values, list) else model_registers(model_id, values)
        out += [model_id, len(registers), *registers]
    return out + ([END_MODEL, 0] if end is None else end)


def data_file(title: str, registers: list[int], note: str = "") -> str:
    """A `serve --data` file: sparse (a read outside the chain answers exception 02, as an
    inverter's does), the chain at 40000, one list a model, each named."""
    lines = [
        f"# {title}",
        "# Written by scripts/make_sunspec_twin.py: run it again rather than edit this.",
        "",
    ]
    if note:
        lines += [f"# {line}" for line in note.splitlines()] + [""]
    lines += [
        "sparse = true",
        "",
        "[holding_registers]",
        f"{BASE} = [0x{MARKER[0]:04X}, 0x{MARKER[1]:04X}]  # SunS",
    ]
    at = 2
    while at < len(registers):
        model_id = registers[at]
        if model_id in (END_MODEL, 0) and at + 2 >= len(registers):
            shown = ", ".join(f"0x{value:04X}" for value in registers[at:])
            lines.append(f"{BASE + at} = [{shown}]  # end of the chain")
            break
        length = registers[at + 1]
        group = definition(model_id)
        name = group["name"] if group else "no SunSpec definition"
        block = registers[at : at + 2 + length]
        lines.append(
            f"# model {model_id} ({name}): id, length {length}, registers {BASE + at + 2}-{BASE + at + 1 + length}"
        )
        body = ", ".join(str(value) for value in block)
        lines.append(f"{BASE + at} = [{_wrapped(body)}]")
        at += 2 + length
    return "\n".join(lines) + "\n"


def _wrapped(text: str, width: int = 96) -> str:
    words, lines, line = text.split(" "), [], ""
    for word in words:
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    lines.append(line)
    return ("\n    " + "\n    ".join(lines) + "\n") if len(lines) > 1 else lines[0]


ZERO_LENGTH_MODELS = 300  # past the walk's bound of models (mbtool/sunspec/discover.py)


def quirks() -> dict[str, tuple[str, list[int], str]]:
    """Each quirk's data file (and nested-groups, the tests' model of nested counted groups):
    what it is, its registers from 40000, and a note."""
    common, inverter = TWIN[0], TWIN[1]
    mppt = TWIN[6]
    short_common = model_registers(1, common[1])[:-1]  # 65 registers: the common model before its Pad
    long_inverter = model_registers(103, inverter[1]) + [0x1234, 0x5678]
    short_inverter = model_registers(103, inverter[1])[:-6]
    mppt_leftover = model_registers(160, mppt[1]) + [0, 0, 0]
    return {
        "no-end-model": (
            "A chain without its end model: the register after the last model answers exception 02 "
            "(SMA, bikeshedder/sunspec #20)",
            chain([common, inverter], end=[]),
            "",
        ),
        "end-0000": (
            "A chain ended by 0x0000 alone: reading the id and length together answers exception 02, "
            "the id alone reads 0 (Kostal, sunspec/models #44)",
            chain([common, inverter], end=[0]),
            "",
        ),
        "model-lengths": (
            "Models whose length on the wire is not their definition's: common model 1 with 65 "
            "registers (no Pad), inverter 103 two registers longer, a second 103 six shorter",
            chain([(1, short_common), (103, long_inverter), (103, short_inverter)]),
            "",
        ),
        "group-count": (
            "An MPPT model 160 whose length holds two modules and 3 registers that make no third "
            "(as a battery's model 803 with 6 registers where a string takes 32: ha-sunspec #62)",
            chain([common, (160, mppt_leftover)]),
            "",
        ),
        "battery-string": (
            "A battery bank's model 803 whose NStr says one string of 32 registers, and 6 registers "
            "after the model's fixed points (an E3DC S10: ha-sunspec #62)",
            chain([common, (803, model_registers(803, {"NStr": 1, "NStrCon": 1}) + [0] * 6)]),
            "",
        ),
        "nested-groups": (
            "Volt-var curves (model 705): two curves of two points each, each count held by a point "
            "of the model (NCrv, NPt), the points a group inside each curve",
            chain([common, (705, VOLT_VAR)]),
            "",
        ),
        "zero-length-models": (
            "A hostile chain: after the common model, 300 models SunSpec does not define, each of "
            "length 0, then the end model; unbounded, a walk of such a chain to register 65535 "
            "took 12,768 reads (issue 40 item 13)",
            chain([common] + [(64998, [])] * ZERO_LENGTH_MODELS),
            "",
        ),
        "unknown-model": (
            "A model id SunSpec does not define (64999, 4 registers) between two it does: shown raw, "
            "the walk goes on",
            chain([common, (64999, [1, 2, 3, 4]), inverter]),
            "",
        ),
    }


def files() -> dict[Path, str]:
    twin = data_file(
        "A SunSpec inverter twin: mbtool serve --data examples/sunspec-twin.toml",
        chain(TWIN),
        "A 10 kW three-phase PV inverter (103) with its nameplate (120), settings (121), status (122),\n"
        "controls (123), two MPPT inputs (160) and a meter at the grid point (203), after the common\n"
        "model (1). Try: mbtool sunspec -p tcp://127.0.0.1:5020 (docs/sunspec.md).",
    )
    out = {REPO / "examples" / "sunspec-twin.toml": twin}
    for name, (title, registers, note) in quirks().items():
        out[REPO / "tests" / "data" / "sunspec" / f"{name}.toml"] = data_file(title, registers, note)
    return out


def main(argv: list[str]) -> int:
    check = "--check" in argv
    stale = []
    for path, text in files().items():
        if check:
            if not path.exists() or path.read_text() != text:
                stale.append(path)
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        print(f"wrote {path.relative_to(REPO)}")
    for path in stale:
        print(f"{path.relative_to(REPO)} is not what scripts/make_sunspec_twin.py makes", file=sys.stderr)
    # Every model laid out as the walk will: the twin has no quirk of its own.
    for model_id, values in TWIN:
        layout = lay_out(model_id, str(model_id), BASE, model_registers(model_id, values))
        assert not layout.warnings, layout.warnings
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
