"""Small helpers below everything else: YAML files, files written atomically, argument checks, angle math."""
