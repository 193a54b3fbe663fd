"""flightkit: flight scripts, capture and onboard estimation for motion-capture drone labs."""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
