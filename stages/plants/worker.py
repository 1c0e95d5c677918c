"""A worker process for the plants stage: `python -m stages.plants.worker`
reads pickled (function, args) jobs from stdin and writes pickled
("ok", result) or ("error", exception) replies, one per job, until stdin
closes. A plain subprocess rather than multiprocessing's spawn, which would
re-run the calling program's main script in the child."""
from __future__ import annotations

import os
import pickle
import sys


def main() -> int:
    replies = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # whatever the libraries print goes to stderr, not into the replies
    jobs = sys.stdin.buffer
    while True:
        try:
            fn, args = pickle.load(jobs)
        except EOFError:
            return 0
        try:
            reply = ("ok", fn(*args))
        except Exception as e:  # the parent raises it in the stage
            reply = ("error", e)
        pickle.dump(reply, replies, protocol=pickle.HIGHEST_PROTOCOL)
        replies.flush()


if __name__ == "__main__":
    sys.exit(main())
