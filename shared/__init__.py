"""crossmodal common library: runtime, messages, keys, robot models, protocols."""
