from services.foxglove.service import FoxgloveService
from shared.runtime import service_main

service_main("foxglove", FoxgloveService)
