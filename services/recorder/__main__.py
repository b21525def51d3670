import sys

from services.recorder.service import RecorderService
from shared.runtime import service_main
from shared.runtime.service import parse_args

# The deployment file is also written into each recording's metadata.
RecorderService.deployment = parse_args("recorder", sys.argv[1:]).deployment
service_main("recorder", RecorderService)
