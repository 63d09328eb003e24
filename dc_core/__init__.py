"""DC core: contracts and machinery shared by every server. It imports no concrete plugin."""
