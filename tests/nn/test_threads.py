"""nn.model.cpu_threads: the cores other processes leave idle, measured now (not the load average,
which still counts the pipeline's own workers of the stage before)."""
import os
import subprocess
import sys
import time

import pytest

from ibr_pipeline.nn import model as M

SPIN = "import time\nt = time.time()\nwhile time.time() - t < 20: pass\n"


def test_requested_count_is_kept():
    assert M.cpu_threads(3) == 3


@pytest.mark.skipif(not os.path.exists("/proc/stat"), reason="needs Linux /proc/stat")
def test_a_spinning_process_takes_a_core():
    quiet = M.busy_cores(0.3)
    assert quiet is not None and quiet >= 0.0
    child = subprocess.Popen([sys.executable, "-c", SPIN])
    try:
        time.sleep(0.3)   # the child is running, not starting
        busy = M.busy_cores(0.3)
        threads = M.cpu_threads()
    finally:
        child.kill()
        child.wait()
    # one spinning process is one core busy (other load on the machine only adds to it)
    assert busy >= 0.8
    assert threads <= max(1, (os.cpu_count() or 1) - 1)


@pytest.mark.skipif(not os.path.exists("/proc/stat"), reason="needs Linux /proc/stat")
def test_own_work_is_not_counted():
    import threading
    quiet = M.busy_cores(0.3)
    stop = time.time() + 0.6

    def spin():
        while time.time() < stop:
            pass

    t = threading.Thread(target=spin)
    t.start()
    try:
        busy = M.busy_cores(0.3)   # this process's own thread spins: not another process
    finally:
        t.join()
    # a spinning thread of ours is a whole core: counted, it would add ~1
    assert quiet is not None and busy is not None and busy < quiet + 0.5
