"""How many threads each library's pool may use for the chain, so that the two cores are not fought over.

The chain runs frame after frame on one worker thread; its heavy calls are OpenCV's (SGBM, ORB, LSD, the
matcher, PnP) and onnxruntime's (the detector). Each library keeps its own pool: left at their defaults, OpenCV
sizes its pool to the cores and onnxruntime its intra-op pool too, so on 2 cores 2 + 2 worker threads plus the
service's intake threads (and any other process) share two cores, and a pool waiting at a barrier for a
descheduled thread stalls the whole call. The rule: OpenCV gets the cores (`opencv`, its calls are long enough
to split, SGBM's rows in stripes), onnxruntime one thread (`onnxruntime`: the detector's net is too small to
split: its CPU time a frame is the same with 1 intra-op thread and with 2; perception.detector also turns its
pool's spinning off). OpenCV's CPU time is the same with 1 or 2 threads; 2 lets a long call finish in about half
the time where the other core is free. The choice is made on CPU time: on a loaded machine wall times say nothing
(docs/measurements.md, "Thread pools on two cores"). In the service the other core is not free: it answers each
frame on arrival and takes the vehicle's streams on other threads, and the vehicle's own processes may share the
machine; OpenCV there gets one thread (`SERVICE_THREADS`), which leaves a core to them (docs/measurements.md,
"Frames answered on arrival"). Call `set_threads` once, at the composition root (the service's pipeline, the
replay's perception source, benchmarks); library code never changes them.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ThreadPlan:
    opencv: int = 2  # cv2.setNumThreads
    onnxruntime: int = 1  # the detector's intra-op threads (inter-op: 1)

    def describe(self) -> str:
        import cv2

        return f"OpenCV {cv2.getNumThreads()} (plan {self.opencv}), onnxruntime intra-op {self.onnxruntime}"


THREADS = ThreadPlan()  # the chain alone on the cores: a replay, a benchmark
SERVICE_THREADS = ThreadPlan(opencv=1)  # the service: a core kept for the answers and the vehicle's streams


def set_threads(plan: ThreadPlan = THREADS) -> ThreadPlan:
    """Apply the plan's OpenCV setting (process-wide); the detector takes `plan.onnxruntime` when it is made."""
    import cv2

    cv2.setNumThreads(plan.opencv)
    return plan
