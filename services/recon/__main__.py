from services.recon.service import ReconService
from shared.runtime import service_main

service_main("recon", ReconService)
