"""What clients can do, one function per action with typed inputs: create, cancel, retry and delete jobs
and scenes. The routes, the scene supervisor and the tests call them alike; they raise
`service.errors.ServiceError` (the app maps it to its HTTP status) and return store rows."""
