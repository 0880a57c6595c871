"""The device layer's error."""


class DeviceError(RuntimeError):
    """An OpenCL device could not be found, a buffer could not be allocated, or a
    program failed to compile (the message holds the compiler's log)."""
