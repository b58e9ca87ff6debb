"""Settings, database and security helpers of the app."""
