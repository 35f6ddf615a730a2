"""moto_server with DynamoDB's per-request atomicity.

Real DynamoDB applies each request (a conditional write, a transaction) atomically. moto's
threaded server does not: a cancelled TransactWriteItems restores every table it touched
from a copy taken when it began, erasing writes other threads made meanwhile, and an
UpdateItem reads and writes an item without a lock. One lock around the item operations
makes each request atomic again, as the service is, without serialising other services
(an SQS long poll still waits on its own thread).
"""

import functools
import sys
import threading

from moto.dynamodb.models import DynamoDBBackend
from moto.server import main

_LOCK = threading.RLock()


def _atomic(method):
    @functools.wraps(method)
    def locked(*args, **kwargs):
        with _LOCK:
            return method(*args, **kwargs)

    return locked


for _name in (
    "put_item",
    "get_item",
    "query",
    "scan",
    "update_item",
    "delete_item",
    "transact_write_items",
    "transact_get_items",
    "batch_get_item",
    "batch_write_item",
):
    setattr(DynamoDBBackend, _name, _atomic(getattr(DynamoDBBackend, _name)))

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
