"""Session-wide test settings."""

from gear.device import limit_torch_threads

# The same torch thread count as `python -m gear` (see limit_torch_threads): the training tests
# then run as the CLI does, and do not slow down ten-fold on a loaded 2-core machine.
limit_torch_threads()
