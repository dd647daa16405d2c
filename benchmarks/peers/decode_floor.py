"""The floor: decode every frame of a clip and convert it to grey, nothing else (PyAV, all threads).

``benchmarks/.peers-venv/bin/python decode_floor.py VIDEO`` prints one JSON line {"frames": n, "seconds": s}.
"""

import json
import sys
import time

t0 = time.perf_counter()
import av  # noqa: E402

with av.open(sys.argv[1]) as c:
    st = c.streams.video[0]
    st.thread_type = "AUTO"  # frame and slice threads: all cores
    n = 0
    for frame in c.decode(st):
        frame.to_ndarray(format="gray")
        n += 1
print(json.dumps({"frames": n, "seconds": time.perf_counter() - t0}))
