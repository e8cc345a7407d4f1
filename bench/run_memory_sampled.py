"""Run a `cell` command in-process with a 5 s sampler of its memory: RSS, VmHWM and glibc's mallinfo2 (all
arenas), and a log of every cell.memory.release_free_heap call the controller makes (RSS before and after, the
free heap before, its time). Output: the file $SAMPLES (JSON lines). Used for issue 16, item 5 (the hires
pillar's peak, docs/benchmarks.md):

    SAMPLES=/tmp/hires.jsonl nice -n 10 /usr/bin/time -v .venv/bin/python bench/run_memory_sampled.py \
        inspect recipes/pillar.yaml --cell recipes/cells/sim_hires.yaml --out RUN
"""

import ctypes
import json
import os
import runpy
import sys
import threading
import time

OUT = open(os.environ["SAMPLES"], "a", buffering=1)
libc = ctypes.CDLL(None)


class MI2(ctypes.Structure):
    _fields_ = [
        (n, ctypes.c_size_t)
        for n in (
            "arena",
            "ordblks",
            "smblks",
            "hblks",
            "hblkhd",
            "usmblks",
            "fsmblks",
            "uordblks",
            "fordblks",
            "keepcost",
        )
    ]


libc.mallinfo2.restype = MI2
PAGE = os.sysconf("SC_PAGE_SIZE")


def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE


def hwm():
    with open("/proc/self/status") as f:
        for l in f:
            if l.startswith("VmHWM"):
                return int(l.split()[1]) * 1024


def mi():
    m = libc.mallinfo2()
    return {"heap": m.arena, "mmapped": m.hblkhd, "used": m.uordblks, "free": m.fordblks, "top": m.keepcost}


def sampler():
    while True:
        OUT.write(
            json.dumps(
                {
                    "t": time.time(),
                    "kind": "sample",
                    "rss": rss(),
                    "hwm": hwm(),
                    **mi(),
                    "cpu": os.times()[:2],
                }
            )
            + "\n"
        )
        time.sleep(5)


threading.Thread(target=sampler, daemon=True).start()

if os.environ.get("TRACE_TRIM", "1") == "1":
    import cell.controller as cc

    orig = cc.release_free_heap

    def traced():
        r0, m0, t0 = rss(), mi(), time.perf_counter()
        c0 = time.process_time()
        res = orig()
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        OUT.write(
            json.dumps(
                {
                    "t": time.time(),
                    "kind": "trim",
                    "thread": threading.current_thread().name,
                    "rss0": r0,
                    "rss1": rss(),
                    "free0": m0["free"],
                    "heap0": m0["heap"],
                    "used0": m0["used"],
                    "dt": dt,
                    "dcpu": dc,
                    "res": res,
                }
            )
            + "\n"
        )
        return res

    cc.release_free_heap = traced

sys.argv = ["cell"] + sys.argv[1:]
runpy.run_module("cell", run_name="__main__", alter_sys=True)
