"""The representations SKED edits, and the registry that names them."""
