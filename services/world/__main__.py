from services.world.service import WorldService
from shared.runtime import service_main

service_main("world", WorldService)
