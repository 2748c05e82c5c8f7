"""`credit ...` under cProfile; the profile is written to $PROF_OUT when the process exits."""

import atexit
import cProfile
import os
import sys

from cluster.cli import main

pr = cProfile.Profile()
atexit.register(lambda: (pr.disable(), pr.dump_stats(os.environ["PROF_OUT"])))
pr.enable()
sys.argv = ["credit", *sys.argv[1:]]
main()
