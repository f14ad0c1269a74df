"""`python -m percept_memory` is `pmem`."""

from percept_memory.cli import main

main()
