"""The station process's CPU priority: its trigger path runs under Linux's real-time FIFO policy.

A station PC also runs the API process, an MES's queries, a browser or a shell. Under the normal
(CFS) scheduler every runnable task shares the cores, so a trigger that wakes up while they run
waits for its turn: on two cores an MES asking 200 requests a second added 2-4 ms to the median
trigger (docs/performance.md). A thread under ``SCHED_FIFO`` runs as soon as it is runnable and is
preempted only by higher real-time priorities, so the station's answer no longer depends on what
else the PC does.

:func:`enter` is called by the station process's main thread before it starts anything: Linux
threads inherit their creator's policy, so the trigger thread, the links' loop, the recorder, the
camera threads and the detection worker processes all run at that priority. Work that must not
compete with the next trigger (the archive's PNG encoding) calls :func:`background` in its own
thread to go back to the normal policy, niced. Short Python work beside it (the live camera
view's frames) calls :func:`beneath`: real-time below the trigger path (see there why).

The station's threads block while they wait (sockets, queues, the cameras); none of them spins.
Linux keeps 5 % of each second for normal tasks whatever real-time threads do
(``/proc/sys/kernel/sched_rt_runtime_us``), so a fault cannot lock the machine up.

Setting the policy needs ``CAP_SYS_NICE`` (root has it; a container gets it with
``cap_add: [SYS_NICE]``) or an ``RLIMIT_RTPRIO`` of at least the priority. When the system refuses,
the station runs at the normal policy, logs a warning once and shows why in its status.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from typing import Any

log = logging.getLogger(__name__)

#: the default real-time priority (1-99): above the kernel's threaded interrupt handlers' 50 is
#: not needed; anything above 0 preempts every normal task
DEFAULT_PRIORITY = 10


def enter(priority: int) -> dict[str, Any]:
    """Put the calling thread (and so every thread and process it starts later) under
    ``SCHED_FIFO`` at ``priority``; 0 leaves the normal policy. Returns the status to show."""
    if not 0 <= priority <= 99:
        raise ValueError(f"a real-time priority is 1-99 (0: off), got {priority}")
    if priority == 0:
        return {"policy": "normal", "priority": 0, "why": "off (trigger priority 0)"}
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as err:
        why = (f"SCHED_FIFO {priority} refused ({err}): give the station CAP_SYS_NICE "
               "(compose: cap_add: [SYS_NICE]) or an RLIMIT_RTPRIO of at least the priority")
        log.warning("station process: normal CPU priority; %s", why)
        return {"policy": "normal", "priority": 0, "why": why}
    log.info("station process: trigger path at SCHED_FIFO priority %d", priority)
    return {"policy": "fifo", "priority": priority}


def background(nice: int = 10) -> None:
    """The calling thread leaves the real-time policy (if it had it) and is niced: it runs only
    when the trigger path and normal tasks leave a core free."""
    with contextlib.suppress(AttributeError, OSError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(AttributeError, OSError):
        # Linux: a thread is a task with its own nice value
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)



def beneath(priority: int = 1) -> None:
    """The calling thread stays real-time when the station's trigger path is, at ``priority``
    (below the trigger path's, above every normal task); otherwise it is niced like
    :func:`background`.

    For short Python work beside the trigger path (the live camera view's frames): a niced
    thread that holds the GIL when the kernel preempts it keeps the trigger thread waiting for
    the GIL until the busy machine's normal tasks let it run again; a real-time thread below the
    trigger path gives the core to a trigger at once and gets it back before any normal task.
    """
    try:
        policy = os.sched_getscheduler(0)
    except (AttributeError, OSError):
        policy = None
    if policy == getattr(os, "SCHED_FIFO", None):
        with contextlib.suppress(OSError):
            os.sched_setparam(0, os.sched_param(priority))
            return
    background()
