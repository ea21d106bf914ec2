"""Group the samples of S sensors into sets taken at the same epoch, by header stamp.

Pure Python (no rclpy), shared by the calibration and corrector nodes. The sensors stream at
the same rate but arrive on separate topics, each in stamp order. The matcher keeps one queue
per sensor; whenever every queue has a sample it compares the heads: if their stamps spread
by at most ``tolerance_s`` they form a set, otherwise the oldest heads (those within the
tolerance of the oldest stamp) belong to an epoch some sensor never delivered, and are
dropped and counted as one incomplete set. This is the "approximate time" policy of
message_filters specialised to equal rates, and costs O(S) per sample.
"""
from collections import deque


class StampMatcher:
    """Match samples of ``n_sensors`` streams by stamp.

    Parameters
    ----------
    n_sensors : int
        Number of streams S.
    tolerance_s : float
        Largest spread (max - min) of the stamps of one set, s. About half a sample period.
    max_queue : int
        Samples kept per stream while another stream is silent; older ones are dropped
        (counted as incomplete sets).

    Attributes
    ----------
    complete : int
        Sets emitted.
    incomplete : int
        Epochs dropped because a sensor's sample was missing.
    out_of_order : int
        Samples dropped because their stamp was older than the previous one of that sensor.
    """

    def __init__(self, n_sensors, tolerance_s, max_queue=1000):
        if n_sensors < 1:
            raise ValueError(f'n_sensors must be >= 1, got {n_sensors}')
        if not tolerance_s > 0:
            raise ValueError(f'tolerance_s must be > 0 s, got {tolerance_s}')
        self.n_sensors = int(n_sensors)
        self.tolerance_s = float(tolerance_s)
        self.max_queue = int(max_queue)
        self._queues = [deque() for _ in range(self.n_sensors)]
        self.complete = 0
        self.incomplete = 0
        self.out_of_order = 0

    def reset(self):
        """Forget queued samples and counters."""
        for q in self._queues:
            q.clear()
        self.complete = self.incomplete = self.out_of_order = 0

    def add(self, j, stamp_s, item):
        """Add the sample ``item`` of sensor ``j`` (0-based) stamped ``stamp_s`` seconds.

        Returns
        -------
        list of (float, list)
            Completed sets: (mean stamp in s, [item of sensor 0, ..., item of sensor S-1]),
            oldest first. Usually empty or one set.
        """
        q = self._queues[j]
        if q and stamp_s < q[-1][0]:
            self.out_of_order += 1
            return []
        q.append((stamp_s, item))
        if len(q) > self.max_queue:
            q.popleft()
            self.incomplete += 1
        out = []
        queues = self._queues
        while all(queues):
            stamps = [qq[0][0] for qq in queues]
            t_min = min(stamps)
            if max(stamps) - t_min <= self.tolerance_s:
                items = [qq.popleft()[1] for qq in queues]
                out.append((sum(stamps) / len(stamps), items))
                self.complete += 1
            else:
                for qq, ts in zip(queues, stamps):
                    if ts - t_min <= self.tolerance_s:
                        qq.popleft()
                self.incomplete += 1
        return out
