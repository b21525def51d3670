from services.policy.service import PolicyService
from shared.runtime import service_main

service_main("policy", PolicyService)
