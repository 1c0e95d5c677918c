"""The two kinds of failure a user sees.

InputError: the user's config or an input file is wrong. One clear message
naming the file and key, exit status 2, nothing written.
StageError: a stage could not produce a valid result (a numerical blow-up,
a broken invariant). The message names the stage, parameter and step; the
half-made artifact is thrown away. Exit status 1.
DeviceError: no OpenCL device can run the kernels (none passes the probe,
WORLDBAKE_CL_DEVICE names none, or a kernel does not build on the device).
The message names each device tried and its error. Exit status 3.
"""


class InputError(Exception):
    pass


class StageError(Exception):
    pass


class DeviceError(Exception):
    pass
