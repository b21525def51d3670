from services.trajopt.service import TrajoptService
from shared.runtime import service_main

service_main("trajopt", TrajoptService)
