"""A backend plugin module that fails to import (the registry must report it, not crash)."""

raise ImportError("this test plugin is broken on purpose")
