from services.recorder.service import RecorderService
from shared.runtime import service_main

service_main("recorder", RecorderService)
