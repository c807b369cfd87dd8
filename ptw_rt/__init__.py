"""ptw-rt: real-time state estimator for a powered two-wheeler (roll, rider torque, tyre stiffness over CAN).

Importing the package keys numba's on-disk cache to the source of every jitted module before numba is
imported (`_numba_cache`): numba's `cache=True` checks only the file of the function it loads, so a
changed callee in another module (say `core/attitude.py` under `core/estimator.py`) would otherwise
leave the caller's stale machine code in the cache, and that stale code would run.
"""

from ptw_rt._numba_cache import key_numba_cache_to_source

key_numba_cache_to_source()
