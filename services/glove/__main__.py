from services.glove.service import GloveService
from shared.runtime import service_main

service_main("glove", GloveService)
