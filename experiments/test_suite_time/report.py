"""The sixth pass's tables from measure.py's logs: `python report.py OUT [--top N]`.

Per file: wall and CPU seconds, the load, the compiles of every process (pytest's and the runs
its tests start). Per program (the persistent cache's key: one lowered module with its shapes
and options): the programs that more than one file compiles, and the program names compiled
under the most distinct keys (the same function at other shapes or settings)."""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path


def load(out: Path):
    files, rows = {}, []
    for timing in sorted(out.glob("*.time")):
        name = timing.name.removesuffix(".time")
        lines = timing.read_text().split("\n")
        if not any(ln.startswith("result") for ln in lines):  # still running
            continue
        wall, user, system = (float(x) for x in lines[0].split()[-3:])
        load_avg = next((ln.split()[1:] for ln in lines if ln.startswith("load")), ["?", "?"])
        result = next((ln[7:] for ln in lines if ln.startswith("result")), "")
        files[name] = dict(wall=wall, cpu=user + system, load=load_avg, result=result)
        log = out / f"{name}.jsonl"
        for line in log.read_text().splitlines() if log.exists() else []:
            row = json.loads(line)
            row["file"] = name
            rows.append(row)
    return files, rows


def main(out: str, top: int = 25) -> None:
    files, rows = load(Path(out))
    per_file = defaultdict(lambda: defaultdict(float))
    pytest_pid = {}
    for r in rows:
        if r["kind"] == "process" and "pytest" in r["argv"]:
            pytest_pid[r["file"]] = r["pid"]
    for r in rows:
        f = per_file[r["file"]]
        if r["kind"] in ("compile", "trace", "lower"):
            f[r["kind"]] += r["s"]
            if r["kind"] == "compile":
                f["n"] += 1
                if r["pid"] != pytest_pid.get(r["file"]):
                    f["sub_compile"] += r["s"]
        elif r["kind"] == "process" and r["pid"] != pytest_pid.get(r["file"]):
            f["procs"] += 1
            f["procs_cpu"] += r["cpu"]

    print(
        "| file | result | CPU s | wall s | load | compiles | XLA compile s | trace s | lower s "
        "| runs started: n, CPU s, their compile s |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    total = defaultdict(float)
    for name, t in sorted(files.items(), key=lambda kv: -kv[1]["cpu"]):
        f = per_file[name]
        print(
            f"| {name.removesuffix('.py')} | {t['result']} | {t['cpu']:.1f} | {t['wall']:.0f} "
            f"| {t['load'][0]}-{t['load'][1]} | {f['n']:.0f} | {f['compile']:.1f} | "
            f"{f['trace']:.1f} | {f['lower']:.1f} | {f['procs']:.0f}, {f['procs_cpu']:.0f}, "
            f"{f['sub_compile']:.0f} |"
        )
        total["cpu"] += t["cpu"]
        for k in ("compile", "trace", "lower", "n"):
            total[k] += f[k]
    print(
        f"| all {len(files)} | | {total['cpu']:.0f} | | | {total['n']:.0f} | "
        f"{total['compile']:.0f} | {total['trace']:.0f} | {total['lower']:.0f} | |\n"
    )

    # programs by key: the compiles that were misses (every file starts from an empty cache)
    by_key = defaultdict(list)
    for r in rows:
        if r["kind"] == "compile" and r.get("key") and not r.get("hit"):
            by_key[r["key"]].append(r)
    dup = []
    for key, rs in by_key.items():
        where = defaultdict(float)
        for r in rs:
            where[r["file"]] = max(where[r["file"]], r["s"])
        if len(where) > 1:
            seconds = sorted(where.values())
            # what compiling it in more than one file costs: all but the cheapest
            dup.append((sum(seconds) - seconds[0], rs[0]["name"], key, dict(where), rs))
    dup.sort(key=lambda d: -d[0])
    print(
        f"Programs (one key) compiled in more than one file: {len(dup)}, "
        f"{sum(d[0] for d in dup):.0f} s beyond each one's first file\n"
    )
    print("| program | s each (max) | files | where (test of the first compile per file) |")
    print("| --- | --- | --- | --- |")
    for _, name, key, where, rs in dup[:top]:
        tests = {}
        for r in rs:
            tests.setdefault(
                r["file"],
                (
                    r["test"].split("::")[-1][:50] or "(collect/fixture)",
                    "run" if r["pid"] != pytest_pid.get(r["file"]) else "",
                ),
            )
        where_text = "; ".join(
            f"{f.removesuffix('.py').removeprefix('test_')}: {t}{' (subprocess)' if s else ''}"
            for f, (t, s) in sorted(tests.items())
        )
        print(f"| {name} `{key[-8:]}` | {max(where.values()):.2f} | {len(where)} | {where_text} |")

    # names under many keys: the same function at other shapes
    by_name = defaultdict(lambda: defaultdict(float))
    files_of = defaultdict(set)
    for key, rs in by_key.items():
        name = rs[0]["name"]
        by_name[name][key] = max(r["s"] for r in rs)
        files_of[name] |= {r["file"] for r in rs}
    named = sorted(by_name.items(), key=lambda kv: -sum(kv[1].values()))
    print("\n| program name | distinct keys | compile s of one each | files |")
    print("| --- | --- | --- | --- |")
    for name, keys in named[:top]:
        print(f"| {name} | {len(keys)} | {sum(keys.values()):.1f} | {len(files_of[name])} |")


if __name__ == "__main__":
    args = sys.argv[1:]
    main(args[0], *(int(a) for a in args[1:]))
