from services.camhub.service import CamhubService
from shared.runtime import service_main

service_main("camhub", CamhubService)
