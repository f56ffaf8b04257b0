"""Scripts that fit product constants: each prints or writes values that are pasted into core/
(the clip rule's coefficients, the indoor fill's elevation gain), and the accuracy benches refit
them without the room they score. Run them through `lightfield bench run NAME`."""
