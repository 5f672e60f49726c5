"""In-repo methods: one folder per method, each exporting METHOD (a bench.api.MethodSpec).
`methods/common/` holds building blocks shared by methods; it is not a method."""
