"""The actuator: parameters, dynamics with analytic derivatives, and the integrator."""
