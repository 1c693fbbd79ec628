"""Generate ``twin_nodes/vehicle/px4_geometry.py`` from a local PX4 git mirror (PX4 1.8 - 1.13 mixer era).

Usage::

    python tools/px4_geometry_table.py /work/.mirror/UM-iRaL+PX4-Autopilot-2026/repo > twin_nodes/vehicle/px4_geometry.py

The chain is the one in ``shared/px4_airframes.md`` section 1.1: SYS_AUTOSTART -> airframe script
(``ROMFS/px4fmu_common/init.d/<ID>_<name>`` at M18, ``init.d/airframes/`` from 2018-12) -> the last
``set MIXER <name>`` after following the scripts it sources (``rc.mc_defaults``' default ``quad_x``
from 2021-10 included) -> the ``R: <key>`` line of ``ROMFS/px4fmu_common/mixers/<name>.main.mix`` ->
the geometry ``.toml`` whose ``[info] key`` is that key (``src/lib/mixer/geometries`` at M18,
``src/lib/mixer/MultirotorMixer/geometries`` from 2019-11).  Only PX4 facts are written: positions
(FRD, as the toml gives them: PX4 normalises the mix, so only their shape matters), spins, names and
the commits read.  VTOL (13000-13999) and airframes whose main mixer has no ``R:`` line are left out,
as are airframes with a multirotor AUX mixer (24001 dodecarotor: 12 rotors over two banks).
"""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib

#: label, PX4 master commit (shared/px4_airframes.md's snapshots of the 1.8 - 1.13 cycles)
SNAPSHOTS = [("M18", "c73944c7a2"), ("M110", "6bfb50df8a"), ("M111", "6c78c62d9d"),
             ("M112", "205beb9526"), ("M113", "52221b0bb7")]
GEOM_DIRS = ("src/lib/mixer/MultirotorMixer/geometries", "src/lib/mixer/geometries")
INIT = "ROMFS/px4fmu_common/init.d"
MIXERS = "ROMFS/px4fmu_common/mixers"


def show(repo: str, commit: str, path: str) -> str | None:
    r = subprocess.run(["git", "--git-dir", repo, "show", f"{commit}:{path}"], capture_output=True, text=True)
    return r.stdout if r.returncode == 0 else None


def ls(repo: str, commit: str, path: str) -> list[str]:
    r = subprocess.run(["git", "--git-dir", repo, "ls-tree", "--name-only", f"{commit}", path + "/"],
                       capture_output=True, text=True)
    return r.stdout.split() if r.returncode == 0 else []


def geometries(repo: str, commit: str) -> dict[str, dict]:
    for d in GEOM_DIRS:
        files = [f for f in ls(repo, commit, d) if f.endswith(".toml")]
        if files:
            break
    out = {}
    for f in files:
        g = tomllib.loads(show(repo, commit, f))
        dflt = g.get("rotor_default", {})
        rotors = []
        for r in g["rotors"]:
            pos = list(r["position"]) + [0.0] * (3 - len(r["position"]))
            spin = r.get("direction", dflt.get("direction"))
            rotors.append((r.get("name", ""), tuple(float(v) for v in pos), 1 if spin == "CCW" else -1,
                           tuple(float(v) for v in r.get("axis", dflt.get("axis", (0.0, 0.0, -1.0)))),
                           float(r.get("Ct", dflt.get("Ct", 1.0))), float(r.get("Cm", dflt.get("Cm", 0.05)))))
        out[g["info"]["key"]] = {"file": f.rsplit("/", 1)[1][:-5], "rotors": rotors}
    return out


SET_MIXER = re.compile(r"^\s*set\s+MIXER\s+(\S+)")
SET_AUX = re.compile(r"^\s*set\s+MIXER_AUX\s+(\S+)")
SOURCE = re.compile(r"^\s*(?:sh|\.)\s+\S*etc/init\.d/(\S+)")


def resolve(repo: str, commit: str, text: str, by_name: dict[str, str], state: dict, depth: int = 0) -> None:
    """Run the script's ``set MIXER``/``MIXER_AUX`` lines in order, following the scripts it sources."""
    for line in text.splitlines():
        if m := SET_MIXER.match(line):
            state["mixer"] = m.group(1).strip('"')
        elif m := SET_AUX.match(line):
            state["aux"] = m.group(1).strip('"')
        elif (m := SOURCE.match(line)) and depth < 5:
            name = m.group(1).split("/")[-1]
            path = by_name.get(name)
            sub = show(repo, commit, path) if path else None
            if sub is not None:
                resolve(repo, commit, sub, by_name, state, depth + 1)


def r_line(repo: str, commit: str, mixer: str | None, bank: str = "main") -> list[str] | None:
    """The tokens after ``R:`` in ``<mixer>.<bank>.mix`` (key, then the scales before 2020-08), or None."""
    if not mixer:
        return None
    mix = show(repo, commit, f"{MIXERS}/{mixer}.{bank}.mix")
    if mix is None:
        return None
    m = re.search(r"^R:[ \t]*(\S.*)$", mix, re.M)
    return m.group(1).split() if m else None


def airframes(repo: str, commit: str) -> dict[int, dict]:
    files = [f for f in ls(repo, commit, INIT) if "/" in f]
    files += ls(repo, commit, INIT + "/airframes")
    by_name = {f.rsplit("/", 1)[1]: f for f in files}
    out = {}
    for name, path in sorted(by_name.items()):
        m = re.match(r"^(\d+)_", name)
        if not m:
            continue
        sid = int(m.group(1))
        if 13000 <= sid <= 13999:
            continue
        text = show(repo, commit, path)
        title = re.search(r"^#\s*@name\s+(.+)$", text, re.M)
        state: dict = {}
        resolve(repo, commit, text, by_name, state)
        cls = re.search(r"^#\s*@class\s+(\S+)", text, re.M)
        if cls and cls.group(1) != "Copter":
            continue
        r = r_line(repo, commit, state.get("mixer"))
        if r is None or r_line(repo, commit, state.get("aux"), "aux") is not None:
            continue
        # R: <key> <roll> <pitch> <yaw> <idle> (x 1/10000) until 2020-08: a negative yaw scale reverses
        # the yaw column, as if every rotor spun the other way (4013 bebop)
        yaw = -1 if len(r) >= 4 and r[3].lstrip("-").isdigit() and int(r[3]) < 0 else 1
        out[sid] = {"script": name, "name": title.group(1).strip() if title else name,
                    "mixer": state["mixer"], "key": r[0], "yaw": yaw}
    return out


def main(repo: str) -> None:
    geoms: dict[str, dict] = {}
    geom_from: dict[str, list[str]] = {}
    frames: dict[int, list] = {}
    for label, commit in SNAPSHOTS:
        for key, g in geometries(repo, commit).items():
            if key in geoms and geoms[key]["rotors"] != g["rotors"]:
                sys.exit(f"geometry {key} differs at {commit}; the table assumes one geometry per key")
            geoms.setdefault(key, g)
            geom_from.setdefault(key, []).append(commit)
        for sid, a in airframes(repo, commit).items():
            rows = frames.setdefault(sid, [])
            if rows and (rows[-1]["mixer"], rows[-1]["key"], rows[-1]["yaw"]) == (a["mixer"], a["key"], a["yaw"]):
                rows[-1]["commits"].append(commit)
            else:
                rows.append(dict(a, commits=[commit]))
    print(f'"""PX4 multirotor geometry of the mixer era (PX4 1.8 - 1.13), generated - do not edit.\n\n'
          f'Generated by ``tools/px4_geometry_table.py`` from PX4 master commits '
          f'{", ".join(f"{c} ({lab})" for lab, c in SNAPSHOTS)}\n'
          f'(github:UM-iRaL/PX4-Autopilot-2026; see shared/px4_airframes.md).\n\n'
          f'``GEOMETRIES``: mixer geometry key -> toml file, commits it was read at, and rotors in MAIN output\n'
          f'order as ``(name, (x, y, z) FRD as in the toml, spin +1 CCW / -1 CW,\n'
          f'thrust axis FRD, Ct, Cm)``.\n'
          f'``AUTOSTART``: SYS_AUTOSTART -> one entry per run of snapshots with the same mixer:\n'
          f'``(airframe script, @name, MIXER, geometry key, yaw sign of the R: line, commits)``; the last entry\n'
          f'is the newest.  Airframes of @class Copter (or none given, M18) only.\n"""\n')
    print("GEOMETRIES = {")
    for key in sorted(geoms):
        g = geoms[key]
        print(f"    {key!r}: {{'file': {g['file']!r}, 'commits': {tuple(geom_from[key])!r}, 'rotors': (")
        for r in g["rotors"]:
            print(f"        {r!r},")
        print("    )},")
    print("}\n\nAUTOSTART = {")
    for sid in sorted(frames):
        print(f"    {sid}: (")
        for a in frames[sid]:
            print(f"        ({a['script']!r}, {a['name']!r}, {a['mixer']!r}, {a['key']!r}, {a['yaw']}, {tuple(a['commits'])!r}),")
        print("    ),")
    print("}")


if __name__ == "__main__":
    main(sys.argv[1])
