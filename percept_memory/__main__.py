"""`python -m percept_memory` is `pmem`."""

from percept_memory.cli import main

if __name__ == "__main__":  # not when a worker process (spawned) imports it again
    main()
