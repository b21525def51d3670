from services.panel.service import PanelService
from shared.runtime import service_main

service_main("panel", PanelService)
