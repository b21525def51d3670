import sys

from services.panel.service import PanelService
from shared.runtime import service_main
from shared.runtime.service import parse_args

# The deployment file names the recorder's directory, the default of the demonstration library.
PanelService.deployment = parse_args("panel", sys.argv[1:]).deployment
service_main("panel", PanelService)
