"""A job's shared state in Redis, split along its concerns: the key layout (keys.py), the
pure policy (policy.py), batch leases and the batch registry (leases.py), and the job
record with the exactly-once merge (record.py)."""

from worker.store import keys
from worker.store.leases import Batch, Leases
from worker.store.policy import Status
from worker.store.record import JobRecord, Jobs

__all__ = ["Batch", "JobRecord", "Jobs", "Leases", "Status", "keys"]
